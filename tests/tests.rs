mod ft;
