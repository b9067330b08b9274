#!/usr/bin/env python3
"""A Marlin 2.1 serial emulator, written from a reading of Marlin's source (GPL; no
code copied): the outside check of tactbench's Marlin driver (issue 21).

It is deliberately structured like the firmware, not like tactbench's own simulator
(src/device/marlin/sim.rs), so the driver is tested against a second, independent
reading of the sources:

- gcode/queue.cpp `get_serial_commands()`: bytes are read only while the command
  ring buffer (BUFSIZE = 4) has room and no command blocks the main loop; a line
  starting with `N` must be last_N + 1 (except M110, whose second `N` is taken),
  must carry `*<checksum>` (XOR of the bytes before `*`, decimal); a failure prints
  `Error:<STR_ERR_...>` with `Last Line: <last_N>`, discards the rest of the receive
  buffer and calls `flush_and_request_resend()`: `Resend: <last_N + 1>` then `ok`
  (the current source prints the `ok`; older 2.0.x did not).
- `ok_to_send()`: `ok` after a command has been processed (G0/G1 once buffered in
  the planner).
- feature/e_parser.h (EMERGENCY_PARSER): M410 / M112 are acted on in the serial
  receive path as the bytes arrive (after an optional `N<n> `), whatever blocks;
  the line still goes through the queue and is answered.
- gcode/motion/G0_G1.cpp + module/motion.cpp: NO_MOTION_BEFORE_HOMING ->
  `homing_needed_error()` prints `echo:Home XYZ first` (MSG_HOME_FIRST "Home %s
  first", only the axes not homed) and the move is skipped; `apply_motion_limits()`
  clamps targets to the soft endstops silently.
- gcode/host/M114.cpp (2.x, no M114_LEGACY): `report_current_position_projected()`:
  `X:.. Y:.. Z:.. E:..` (logical current_position, 2 decimals) and ` Count X:.. Y:..
  Z:..` (planner.position in steps): both *planned*, so only meaningful after M400.
- gcode/gcode.cpp `host_keepalive()`: `echo:busy: processing` every 2 s
  (DEFAULT_KEEPALIVE_INTERVAL) while a command blocks (M400 = planner.synchronize(),
  G28).
- gcode/host/M110.cpp, M115.cpp (FIRMWARE_NAME + Cap: lines), config/M92.cpp,
  config/M200-M205 (M203 report), geometry/M211.cpp (2.1 report style),
  control/M999 (clears a Stopped state), M112 -> kill(): `Error:Printer halted.
  kill() called!` and nothing more until a reset; unknown commands: `echo:Unknown
  command: "<cmd>"` (STR_UNKNOWN_COMMAND) and `ok`.
- Motion: constant speed per block (no acceleration; Marlin's planner is not
  modelled), speed = min(F, per-axis M203 limits), positions in whole steps.

Usage (the #[ignore]d tests in tests/marlin.rs start it; manual trials too):
  python3 tests/marlin_emulator/emulator.py --link /tmp/marlin [--record T.txt]
      [--unhomed] [--drop-ok N] [--garble-reply N] [--corrupt-line N]
      [--drop-ok-p P] [--garble-p P] [--corrupt-p P] [--seed S]
Runs until stdin closes. Needs only the Python standard library.
--drop-ok N: the `ok` of the N-th executed command is not sent (lost);
--garble-reply N: the first reply line of the N-th executed command gets one byte 0xFF;
--corrupt-line N: the N-th numbered line received is treated as corrupted on the wire
  (checksum mismatch -> Error + Resend + ok).
--drop-ok-p P, --garble-p P, --corrupt-p P: the same three faults, each executed
  command's `ok` / first reply line, or each numbered line received, with probability
  P, drawn from Python's `random.Random(--seed)` (reproducible; issue 29's line-noise
  cycles);
--record PATH: writes what the host sent (`> `) and what the emulator answered (`< `)
  in the transcript format of protocols/transcripts/ (device lines joined per burst).
"""

import argparse
import os
import pty
import random
import select
import sys
import time
import tty

BUFSIZE = 4
KEEPALIVE_S = 2.0
STEPS = [80.0, 80.0, 400.0]
MAX_FEED = [300.0, 300.0, 10.0]  # mm/s (M203)
SOFT_MIN = [0.0, 0.0, 0.0]
SOFT_MAX = [300.0, 300.0, 100.0]
HOME = [0.0, 0.0, 100.0]  # z homes to its maximum (an indenter must not home down)
HOMING_FEED = 50.0


def xor(b):
    c = 0
    for x in b:
        c ^= x
    return c


class Marlin:
    def __init__(self, args, write):
        self.a = args
        self.write_raw = write
        self.rx = bytearray()  # serial receive buffer (bytes not yet read by the queue)
        self.ring = []  # command ring buffer (lines, without N and *)
        self.last_n = 0
        self.homed = [not args.unhomed] * 3
        self.soft = True
        self.relative = False
        self.current = list(HOME)  # current_position (logical = native here)
        self.pos = list(HOME)  # where the steppers are
        self.blocks = []  # planner blocks: [target, speed]
        self.block_t0 = None
        self.blocking = None  # 'M400' | 'G28'
        self.last_keepalive = 0.0
        self.killed = False
        self.stopped = False
        self.executed = 0
        self.numbered_seen = 0
        self.ep_line = bytearray()
        self.feed = 50.0
        self.rng = random.Random(args.seed)
        self.faults = 0

    def out(self, text):
        self.write_raw(text.encode("latin-1"))

    # -- motion ---------------------------------------------------------------
    def steps_of(self, p):
        return [int(round(p[i] * STEPS[i])) for i in range(3)]

    def snap(self, p):
        s = self.steps_of(p)
        return [s[i] / STEPS[i] for i in range(3)]

    def plan(self, target, speed):
        d = [target[i] - self.current[i] for i in range(3)]
        length = sum(x * x for x in d) ** 0.5
        if length == 0:
            return
        for i in range(3):
            if d[i] != 0:
                speed = min(speed, MAX_FEED[i] * length / abs(d[i]))
        self.blocks.append([list(self.current), list(target), speed])
        self.current = list(target)

    def run_steppers(self, now):
        while self.blocks:
            start, target, speed = self.blocks[0]
            if self.block_t0 is None:
                self.block_t0 = now
            length = sum((target[i] - start[i]) ** 2 for i in range(3)) ** 0.5
            t = now - self.block_t0
            if t * speed >= length:
                self.pos = list(target)
                self.blocks.pop(0)
                self.block_t0 = self.block_t0 + length / speed
                continue
            f = t * speed / length
            self.pos = [start[i] + (target[i] - start[i]) * f for i in range(3)]
            return
        self.block_t0 = None

    def quickstop(self):
        # quickstop_stepper(): planner.quick_stop(); set_current_from_steppers_for_axis(ALL)
        self.blocks = []
        self.block_t0 = None
        self.pos = self.snap(self.pos)
        self.current = list(self.pos)

    def kill(self):
        self.quickstop()
        self.killed = True
        self.out("Error:Printer halted. kill() called!\n")

    # -- serial receive path (ISR + emergency parser) -------------------------
    def receive(self, data):
        if self.killed:
            return
        for b in data:
            self.rx.append(b)
            if b in (10, 13):
                line = bytes(self.ep_line).decode("latin-1").strip()
                self.ep_line = bytearray()
                body = line
                if body.startswith("N"):
                    i = 1
                    while i < len(body) and (body[i].isdigit() or body[i] == "-"):
                        i += 1
                    body = body[i:].lstrip()
                if body.startswith("M112"):
                    self.kill()
                    return
                if body.startswith("M410"):
                    self.quickstop()
            else:
                self.ep_line.append(b)

    # -- the main loop --------------------------------------------------------
    def loop(self, now):
        if self.killed:
            return
        self.run_steppers(now)
        if self.blocking:
            if self.blocks:
                if now - self.last_keepalive >= KEEPALIVE_S:
                    self.last_keepalive = now
                    self.out("echo:busy: processing\n")
                return
            if self.blocking == "G28":
                self.homed = [True] * 3
                self.current = self.snap(HOME)
                self.pos = list(self.current)
            self.blocking = None
            self.ok()
        self.get_serial_commands()
        while self.ring and not self.blocking and not self.killed:
            self.process(self.ring.pop(0))
            self.get_serial_commands()

    def get_serial_commands(self):
        while len(self.ring) < BUFSIZE:
            i = next((k for k, b in enumerate(self.rx) if b in (10, 13)), None)
            if i is None:
                return
            raw = bytes(self.rx[:i]).decode("latin-1")
            del self.rx[: i + 1]
            cmd = raw.strip(" ")
            if ";" in cmd:
                cmd = cmd[: cmd.index(";")]
            cmd = cmd.strip()
            if not cmd:
                continue
            if cmd.startswith("N"):
                self.numbered_seen += 1
                npos = cmd
                m110 = "M110" in cmd
                if m110:
                    j = cmd.find("N", 4)
                    if j >= 0:
                        npos = cmd[j:]
                digits = ""
                for ch in npos[1:]:
                    if ch.isdigit() or (ch == "-" and not digits):
                        digits += ch
                    else:
                        break
                n = int(digits) if digits not in ("", "-") else 0
                if n != self.last_n + 1 and not m110:
                    self.line_error("Line Number is not Last Line Number+1, Last Line: ")
                    return
                if "*" not in cmd:
                    self.line_error("No Checksum with line number, Last Line: ")
                    return
                star = cmd.rindex("*")
                try:
                    given = int(cmd[star + 1 :].strip())
                except ValueError:
                    given = -1
                corrupt = self.a.corrupt_line == self.numbered_seen or (
                    self.a.corrupt_p > 0 and self.rng.random() < self.a.corrupt_p
                )
                self.faults += 1 if corrupt else 0
                if corrupt or given != xor(cmd[:star].encode("latin-1")):
                    self.line_error("checksum mismatch, Last Line: ")
                    return
                self.last_n = n
                body = cmd[:star]
                k = 1
                while k < len(body) and (body[k].isdigit() or body[k] == "-"):
                    k += 1
                cmd = body[k:].strip()
            self.ring.append(cmd)

    def line_error(self, msg):
        self.out("Error:" + msg + str(self.last_n) + "\n")
        self.rx.clear()  # "Clear out the RX buffer"
        self.out("Resend: " + str(self.last_n + 1) + "\n")
        self.out("ok\n")

    def ok(self, text=""):
        self.reply(text + "ok\n")

    def reply(self, text):
        # Faults are counted per executed command.
        if self.a.drop_ok and self.executed == self.a.drop_ok and text.endswith("ok\n"):
            text = text[: -len("ok\n")]
            self.a.drop_ok = 0
        if self.a.garble_reply and self.executed == self.a.garble_reply and text:
            text = "\xff" + text[1:]
            self.a.garble_reply = 0
        if self.a.drop_ok_p > 0 and text.endswith("ok\n") and self.rng.random() < self.a.drop_ok_p:
            text = text[: -len("ok\n")]
            self.faults += 1
        if self.a.garble_p > 0 and text and self.rng.random() < self.a.garble_p:
            text = "\xff" + text[1:]
            self.faults += 1
        self.out(text)

    def param(self, words, letter):
        for w in words:
            if w[:1].upper() == letter:
                try:
                    return float(w[1:])
                except ValueError:
                    return None
        return None

    def process(self, cmd):
        self.executed += 1
        words = cmd.split()
        code = words[0].upper()
        args = words[1:]
        if code in ("G0", "G1", "G00", "G01"):
            need = "".join("XYZ"[i] for i in range(3) if not self.homed[i])
            if need:
                self.reply("echo:Home " + need + " first\nok\n")
                return
            target = list(self.current)
            for i, l in enumerate("XYZ"):
                v = self.param(args, l)
                if v is not None:
                    target[i] = target[i] + v if self.relative else v
            f = self.param(args, "F")
            if f is not None and f > 0:
                self.feed = f / 60.0
            if self.soft:
                target = [min(max(target[i], SOFT_MIN[i]), SOFT_MAX[i]) for i in range(3)]
            speed = self.feed if code in ("G1", "G01") else min(MAX_FEED)
            self.plan(self.snap(target), speed)
            self.ok()
        elif code == "G28":
            self.plan([self.current[0], self.current[1], HOME[2]], HOMING_FEED)
            self.plan(list(HOME), HOMING_FEED)
            self.blocking = "G28"
            self.last_keepalive = time.monotonic()
        elif code == "M400":
            self.blocking = "M400"
            self.last_keepalive = time.monotonic()
        elif code == "M410":
            self.quickstop()
            self.ok()
        elif code == "M112":
            self.kill()
        elif code == "M114":
            p = self.current
            s = self.steps_of(p)
            self.reply(
                "X:%.2f Y:%.2f Z:%.2f E:0.00 Count X:%d Y:%d Z:%d\nok\n"
                % (p[0], p[1], p[2], s[0], s[1], s[2])
            )
        elif code == "M115":
            self.reply(
                "FIRMWARE_NAME:Marlin 2.1.2.1 (emulator) SOURCE_CODE_URL:github.com/MarlinFirmware/Marlin "
                "PROTOCOL_VERSION:1.0 MACHINE_TYPE:3D Printer EXTRUDER_COUNT:1 "
                "UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff\n"
                "Cap:SERIAL_XON_XOFF:0\nCap:EEPROM:1\nCap:AUTOREPORT_TEMP:1\n"
                "Cap:EMERGENCY_PARSER:1\nCap:SOFTWARE_POWER:0\nok\n"
            )
        elif code == "M92" and not args:
            self.reply(
                "echo:; Steps per unit:\necho:  M92 X%.2f Y%.2f Z%.2f E93.00\nok\n" % tuple(STEPS)
            )
        elif code == "M203" and not args:
            self.reply(
                "echo:; Max feedrates (units/s):\necho:  M203 X%.2f Y%.2f Z%.2f E25.00\nok\n"
                % tuple(MAX_FEED)
            )
        elif code == "M211":
            s = self.param(args, "S")
            if s is not None:
                self.soft = s != 0
                self.ok()
            else:
                self.reply(
                    "echo:; Soft Endstops:\necho:  M211 S%d ; %s\n"
                    "echo:  Min:  X%.2f Y%.2f Z%.2f   Max:  X%.2f Y%.2f Z%.2f\nok\n"
                    % ((1 if self.soft else 0, "ON" if self.soft else "OFF") + tuple(SOFT_MIN) + tuple(SOFT_MAX))
                )
        elif code == "M110":
            n = self.param(args, "N")
            if n is not None:
                self.last_n = int(n)
            self.ok()
        elif code in ("G21", "M108"):
            self.ok()
        elif code == "G90":
            self.relative = False
            self.ok()
        elif code == "G91":
            self.relative = True
            self.ok()
        elif code == "M999":
            self.stopped = False
            self.ok()
        else:
            self.reply('echo:Unknown command: "%s"\nok\n' % cmd)


class Recorder:
    def __init__(self, path):
        self.f = open(path, "w") if path else None
        self.host = bytearray()

    def esc(self, b):
        s = ""
        for x in b:
            if x == 10:
                s += "\\n"
            elif x == 13:
                s += "\\r"
            elif x == 92:
                s += "\\\\"
            elif 32 <= x < 127:
                s += chr(x)
            else:
                s += "\\x%02X" % x
        return s

    def host_bytes(self, b):
        if self.f:
            self.f.write("> " + self.esc(b) + "\n")
            self.f.flush()

    def device_bytes(self, b):
        if self.f and b:
            self.f.write("< " + self.esc(b) + "\n")
            self.f.flush()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--link", required=True)
    ap.add_argument("--record")
    ap.add_argument("--unhomed", action="store_true")
    ap.add_argument("--drop-ok", type=int, default=0)
    ap.add_argument("--garble-reply", type=int, default=0)
    ap.add_argument("--corrupt-line", type=int, default=0)
    ap.add_argument("--drop-ok-p", type=float, default=0.0)
    ap.add_argument("--garble-p", type=float, default=0.0)
    ap.add_argument("--corrupt-p", type=float, default=0.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--boot-delay", type=float, default=0.2)
    a = ap.parse_args()

    master, slave = pty.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)
    if os.path.islink(a.link):
        os.remove(a.link)
    os.symlink(name, a.link)
    rec = Recorder(a.record)

    def write(b):
        rec.device_bytes(b)
        os.write(master, b)

    m = Marlin(a, write)
    print("serving on " + name, flush=True)
    t0 = time.monotonic()
    booted = False
    try:
        while True:
            r, _, _ = select.select([master, sys.stdin], [], [], 0.002)
            now = time.monotonic()
            if sys.stdin in r:
                if not os.read(sys.stdin.fileno(), 1024):
                    break
            if master in r:
                try:
                    data = os.read(master, 4096)
                except OSError:
                    data = b""
                if data:
                    rec.host_bytes(data)
                    if booted:
                        m.receive(data)
            if not booted and now - t0 >= a.boot_delay:
                booted = True
                write(
                    b"start\necho:Marlin 2.1.2.1\n\necho: Last Updated: 2023-07-11 | Author: (emulator)\n"
                    b"echo:Compiled: Jul 11 2023\necho: Free Memory: 2914  PlannerBufferBytes: 1488\n"
                )
            if booted:
                m.loop(now)
    finally:
        os.remove(a.link)


if __name__ == "__main__":
    main()
