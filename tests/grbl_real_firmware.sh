#!/bin/sh
# Builds the real GRBL 1.1h firmware for the PC and runs tactbench's ignored
# real-firmware tests (tests/stage.rs `real_firmware::`) against it.
#
# Usage: tests/grbl_real_firmware.sh GRBL_SRC GRBL_SIM_SRC [BUILD_DIR] [--record]
#   GRBL_SRC      a checkout of https://github.com/gnea/grbl (1.1h)
#   GRBL_SIM_SRC  a checkout of https://github.com/grbl/grbl-sim
#   BUILD_DIR     where to build (default /tmp/tactbench-grbl-build); keep it
#                 outside this repository: GRBL is GPL, nothing of it is copied here
#   --record      rewrite protocols/transcripts/grbl_real_*.txt from the run
#
# Fetches nothing. Needs a C compiler, make and socat (apt-get install socat).
# The tests start a fresh firmware instance each (its own EEPROM file = GRBL's
# default settings) with:
#   socat PTY,raw,echo=0,link=DIR/tty "EXEC:'grbl_sim.exe -n -s /dev/null -b /dev/null',pty,raw,echo=0"
# grbl-sim reads stdin through stdio buffering, which delays every reply by one
# command on a pty: the build unbuffers stdin and stdout (its commented setvbuf line).
# On a loaded machine the firmware runs slower than real time and may garble a line.
set -eu
[ $# -ge 2 ] || { sed -n '2,20p' "$0"; exit 2; }
GRBL_SRC=$1; SIM_SRC=$2; BUILD=${3:-/tmp/tactbench-grbl-build}
RECORD=""; for a in "$@"; do [ "$a" = "--record" ] && RECORD=1; done
case "$BUILD" in --record) BUILD=/tmp/tactbench-grbl-build;; esac
REPO=$(cd "$(dirname "$0")/.." && pwd)
rm -rf "$BUILD"; mkdir -p "$BUILD"
cp -r "$GRBL_SRC" "$BUILD/grbl"
# grbl-sim goes inside the firmware's source folder (grbl/grbl/grbl-sim).
cp -r "$SIM_SRC" "$BUILD/grbl/grbl/grbl-sim"
cd "$BUILD/grbl/grbl/grbl-sim"
sed -i 's|^ *//setvbuf(stdout, NULL, _IONBF, 1);| setvbuf(stdout, NULL, _IONBF, 0); setvbuf(stdin, NULL, _IONBF, 0);|' main.c
grep -q 'setvbuf(stdin, NULL, _IONBF, 0)' main.c || { echo "could not unbuffer grbl-sim's main.c" >&2; exit 1; }
make new FLAGS="-g -O2 -fcommon" > "$BUILD/make.log" 2>&1 || { tail -20 "$BUILD/make.log"; exit 1; }
export TACTBENCH_GRBL_SIM="$BUILD/grbl/grbl/grbl-sim/grbl_sim.exe"
echo "built $TACTBENCH_GRBL_SIM"
cd "$REPO"
if [ -n "$RECORD" ]; then export TACTBENCH_GRBL_RECORD_DIR="$REPO/protocols/transcripts"; fi
# One at a time: each test runs its own firmware instance in real time.
cargo test --test integration stage::real_firmware:: -- --ignored --test-threads=1
