"""Builds Bota serial frames the way the vendor's example reads them, for the
`#[ignore]`d test `ft::bota_frames_built_from_the_vendor_layout_decode` (tests/ft.rs).

Layout and CRC exactly as tud-phi/bota_ft_sensors `python/bota_serial_example.py`
unpacks them: header b'\\xAA', 34 payload bytes (`struct` native little-endian 'H' status
at 0, 'f' Fx Fy Fz Mx My Mz at 2..26, 'I' timestamp at 26, 'f' temperature at 30), then
the CRC as `struct.unpack_from('H', crc_frame)` compares it with
`crc.Calculator(Configuration(16, 0x1021, 0xFFFF, 0xFFFF, True, True)).checksum(payload)`.
Needs `pip install crc`. Prints one line per frame: the frame in hex, then the values it
packed (status, six floats, timestamp, temperature) as JSON.

    python3 tests/bota_vendor/frames.py
"""

import json
import struct

from crc import Calculator, Configuration

CALC = Calculator(Configuration(16, 0x1021, 0xFFFF, 0xFFFF, True, True))

CASES = [
    (0, [1.5, -2.25, 12.34, 0.125, -0.05, 0.3], 123456, 25.5),
    (0, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0, 24.0),
    (2, [150.0, -3.0, 999.5, 1.0, 2.0, -3.0], 4294967295, 31.25),  # overrange bit
    (4, [-1e-3, 2e-3, -7.5, 0.01, -0.02, 0.03], 10000, 19.75),  # invalid bit
    (1, [3.0, 4.0, 5.0, 0.3, 0.4, 0.5], 20000, 26.0),  # app took too long
]

for status, values, ts, temp in CASES:
    payload = struct.pack("<H6fIf", status, *values, ts, temp)
    assert len(payload) == 34
    crc = CALC.checksum(payload)
    frame = b"\xAA" + payload + struct.pack("<H", crc)
    # Check against the example's own reading code path.
    assert struct.unpack_from("H", frame[35:37], 0)[0] == CALC.checksum(frame[1:35])
    back = [struct.unpack_from("f", payload, 2 + 4 * i)[0] for i in range(6)]
    print(frame.hex(), json.dumps({"status": status, "values": back, "timestamp": ts, "temperature": struct.unpack_from("f", payload, 30)[0]}))
