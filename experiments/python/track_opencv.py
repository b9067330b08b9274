"""Track frames read by OpenCV and print the force sum per frame.

    python experiments/python/track_opencv.py SENSOR.toml REFERENCE.png FRAME.png...

e.g. with the committed paper run (from the repository root):
    python experiments/python/track_opencv.py experiments/paper_sensor.toml \
        reports/paper/runs/fig7_magnitude/frames/reference.png \
        reports/paper/runs/fig7_magnitude/frames/00*_0.png

cv2.imread gives BGR frames: channels="bgr" says so (no copy is made). Needs
`pip install . opencv-python-headless`.
"""

import sys

import cv2

import tactbench


def main(argv):
    if len(argv) < 3:
        sys.exit(__doc__)
    sensor = tactbench.Sensor(argv[0])
    reference = cv2.imread(argv[1], cv2.IMREAD_COLOR)
    if reference is None:
        sys.exit(f"cannot read {argv[1]}")
    tracker = tactbench.Tracker(sensor, reference, channels="bgr")
    solver = tactbench.Solver(sensor, "pinv")
    for path in argv[2:]:
        frame = cv2.imread(path, cv2.IMREAD_COLOR)
        if frame is None:
            sys.exit(f"cannot read {path}")
        tracks = tracker.track(frame)
        forces = solver.solve(tracks)
        ok = (tracks["status"] == "ok").sum()
        fx, fy, fz = forces["fsum_n"]
        print(f"{path}: {ok} of {len(tracks['status'])} markers ok, F_sum = ({fx:.4f}, {fy:.4f}, {fz:.4f}) N")


if __name__ == "__main__":
    main(sys.argv[1:])
