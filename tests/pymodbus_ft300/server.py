#!/usr/bin/env python3
"""A Robotiq FT 300 on a pseudo-terminal, served by a real Modbus RTU stack (pymodbus).

Used only by the ignored tests in `tests/ft.rs` (`ft300_against_pymodbus_*`), which run
it when the environment variable `TACTBENCH_PYTHON` names a Python with pymodbus:

    pip install pymodbus pyserial
    TACTBENCH_PYTHON=python3 cargo test --test integration ft::ft300_against_pymodbus -- --ignored

By hand:

    python3 tests/pymodbus_ft300/server.py --link /tmp/ft300 [--drop-echo] [--streaming]
    tactbench ft info --protocol ft300 --port /tmp/ft300

Layout: pymodbus (RTU framer, slave 9) serves one end of an inner pseudo-terminal pair;
a relay thread joins its other end to the pseudo-terminal the host opens (`--link`),
playing the part of the sensor's own firmware around the Modbus stack:

- register map as Robotiq's `rq_sensor_com` reads it: 180-185 wrench (int16, 0.01 N,
  0.001 N.m), 410 stream control (only 0x0200 accepted, exception 03 otherwise),
  500-502 firmware (3 letters, then major, minor, patch bytes), 510-513 serial
  number (3 characters in 510 high, 510 low, 511 high; then a 32-bit number, register
  513 the high word and 512 the low word), 514 production year. Any other register
  is invalid (exception 02).
- after pymodbus accepted the write of 0x0200 to 410, the relay sends a 16-byte stream
  frame (0x20 0x4E, six int16 little-endian, CRC-16/MODBUS little-endian) every 10 ms;
  while streaming, host bytes do not reach the Modbus stack, and a run of 0xFF bytes
  (the host's "jam signal", Robotiq sends 50) stops the stream.
- `--drop-echo`: the relay loses the Modbus reply to that write (the stream still
  starts), as seen on real links.
- `--streaming`: the sensor is already streaming when the host connects (left so by an
  earlier session).
- `--garble-stream`: every frame has a bad CRC (a stream that never confirms).

Prints `ready <link>` on stdout once serving. Stops when killed or after
`--duration-s`.
"""

import argparse
import asyncio
import os
import select
import sys
import threading
import time
import tty

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

SLAVE = 9
REG_STREAM = 410
STREAM_START = 0x0200
FRAME_PERIOD_S = 0.010
JAM_RUN = 16


def crc16(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def to_u16(v: int) -> int:
    return v & 0xFFFF


class Firmware:
    """The sensor firmware around the Modbus stack: stream state and the relay."""

    def __init__(self, args, raw):
        self.args = args
        self.raw = raw
        self.streaming = args.streaming
        self.lock = threading.Lock()
        self.drop_next_echo = False
        self.stream_due = time.monotonic()

    async def action(self, function_code, start_address, address, count, registers, set_values):
        """pymodbus hook, called for every register access."""
        if set_values is not None and address <= REG_STREAM < address + count:
            value = set_values[REG_STREAM - address]
            if value != STREAM_START:
                return ExcCodes.ILLEGAL_VALUE
            with self.lock:
                if not self.streaming:
                    self.streaming = True
                    self.stream_due = time.monotonic() + FRAME_PERIOD_S
                self.drop_next_echo = self.args.drop_echo
        return None

    def frame(self) -> bytes:
        body = bytes([0x20, 0x4E]) + b"".join(to_u16(v).to_bytes(2, "little") for v in self.raw)
        crc = crc16(body)
        if self.args.garble_stream:
            crc ^= 0x0101
        return body + crc.to_bytes(2, "little")

    def relay(self, host_fd, modbus_fd, stop):
        """Moves bytes between the host's pty and the Modbus stack's pty."""
        ff_run = 0
        while not stop.is_set():
            with self.lock:
                streaming = self.streaming
                due = self.stream_due
            timeout = max(0.0, due - time.monotonic()) if streaming else 0.05
            ready, _, _ = select.select([host_fd, modbus_fd], [], [], timeout)
            if host_fd in ready:
                try:
                    data = os.read(host_fd, 4096)
                except OSError:
                    data = b""
                forward = bytearray()
                for b in data:
                    ff_run = ff_run + 1 if b == 0xFF else 0
                    with self.lock:
                        if self.streaming and ff_run >= JAM_RUN:
                            self.streaming = False
                        elif not self.streaming:
                            forward.append(b)
                if forward:
                    os.write(modbus_fd, bytes(forward))
            if modbus_fd in ready:
                data = os.read(modbus_fd, 4096)
                with self.lock:
                    drop = self.drop_next_echo and len(data) >= 2 and data[1] == 0x10
                    if drop:
                        self.drop_next_echo = False
                if not drop:
                    os.write(host_fd, data)
            with self.lock:
                now = time.monotonic()
                while self.streaming and self.stream_due <= now:
                    os.write(host_fd, self.frame())
                    self.stream_due += FRAME_PERIOD_S


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--link", required=True, help="symlink to create to the host's pty")
    p.add_argument("--serial-prefix", default="FTS", help="3 characters (registers 510-511)")
    p.add_argument("--serial-number", type=int, default=1234, help="32-bit (registers 512-513)")
    p.add_argument("--year", type=int, default=2019)
    p.add_argument("--firmware", default="FTS-3.0.4", help="LLL-major.minor.patch")
    p.add_argument("--wrench", default="1.5,-2.25,12.34,0.125,-0.05,0.3",
                   help="Fx,Fy,Fz (N),Mx,My,Mz (N.m)")
    p.add_argument("--drop-echo", action="store_true")
    p.add_argument("--streaming", action="store_true")
    p.add_argument("--garble-stream", action="store_true")
    p.add_argument("--duration-s", type=float, default=None)
    return p.parse_args()


def main():
    args = parse_args()
    w = [float(x) for x in args.wrench.split(",")]
    raw = [round(w[i] * 100) for i in range(3)] + [round(w[i] * 1000) for i in range(3, 6)]
    letters, version = args.firmware.split("-")
    major, minor, patch = (int(x) for x in version.split("."))
    fw = letters.encode()[:3]
    prefix = args.serial_prefix.encode()[:3].ljust(3, b"\0")
    n = args.serial_number & 0xFFFFFFFF
    firmware = Firmware(args, raw)
    device = SimDevice(
        id=SLAVE,
        simdata=[
            SimData(address=180, values=[to_u16(v) for v in raw], datatype=DataType.REGISTERS),
            SimData(address=REG_STREAM, values=[0], datatype=DataType.REGISTERS),
            SimData(
                address=500,
                values=[fw[0] << 8 | fw[1], fw[2] << 8 | major, minor << 8 | patch],
                datatype=DataType.REGISTERS,
            ),
            SimData(
                address=510,
                values=[prefix[0] << 8 | prefix[1], prefix[2] << 8, n & 0xFFFF, n >> 16],
                datatype=DataType.REGISTERS,
            ),
            SimData(address=514, values=[args.year], datatype=DataType.REGISTERS),
        ],
        action=firmware.action,
    )
    host_master, host_slave = os.openpty()
    modbus_master, modbus_slave = os.openpty()
    for fd in (host_master, host_slave, modbus_master, modbus_slave):
        tty.setraw(fd)
    # Keep both slave ends open: the masters then never see a hang-up when the host
    # closes and reopens its end.
    if os.path.lexists(args.link):
        os.unlink(args.link)
    os.symlink(os.ttyname(host_slave), args.link)
    stop = threading.Event()
    relay = threading.Thread(
        target=firmware.relay, args=(host_master, modbus_master, stop), daemon=True
    )
    relay.start()

    async def serve():
        server = ModbusSerialServer(
            device,
            framer=FramerType.RTU,
            port=os.ttyname(modbus_slave),
            baudrate=19200,
        )
        task = asyncio.create_task(server.serve_forever())
        await asyncio.sleep(0.2)
        print(f"ready {args.link}", flush=True)
        if args.duration_s is not None:
            await asyncio.sleep(args.duration_s)
            await server.shutdown()
        else:
            await task

    try:
        asyncio.run(serve())
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        if os.path.lexists(args.link):
            os.unlink(args.link)


if __name__ == "__main__":
    sys.exit(main())
