"""Serve LoomDeBWiles/cof_tester's Net F/T sensor simulator on loopback, for the
`#[ignore]`d test `ft::netft_against_cof_tester_records_a_transcript` (tests/ft.rs).

The simulator is third-party code (MIT) and is not in this repository: fetch it
(github:LoomDeBWiles/cof_tester), extract its `src/` directory and point
TACTBENCH_COF_TESTER at it. Needs numpy. Run by hand:

    TACTBENCH_COF_TESTER=/tmp/ft-outside/src python3 tests/netft_cof_tester/serve.py

What this harness changes, and nothing else: the sockets bind 127.0.0.1 with ports
chosen by the OS (cof_tester binds every interface on fixed ports), its own loss and
reorder injection is set from COF_LOSS / COF_REORDER (probabilities), and the signal is
made constant (`signal_frequency_hz = 0`, `noise_stddev = 0`), so every record carries
the same counts: amplitude x sin(0, pi/3, 2pi/3, pi, 4pi/3, 5pi/3) truncated to int32
(0, 86602, 86602, 0, -86602, -86602 at amplitude 100000; Tx = 100000 sin(pi) = 1.2e-11
truncates to 0). Prints one JSON line with the ports, then serves until stdin closes.
"""

import json
import os
import socket
import sys
import threading
from http.server import HTTPServer

sys.path.insert(0, os.environ.get("TACTBENCH_COF_TESTER", "."))

from gsdv.diagnostics.sensor_simulator import (  # noqa: E402
    FaultConfig,
    SensorSimulator,
    SimulatorConfig,
)


class LoopbackSimulator(SensorSimulator):
    """cof_tester's simulator with its three sockets on 127.0.0.1, OS-chosen ports."""

    def start(self):
        self.state.running = True
        self._udp_socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp_socket.bind(("127.0.0.1", 0))
        self._udp_thread = threading.Thread(target=self._handle_udp, daemon=True)
        self._udp_thread.start()
        self._tcp_socket = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._tcp_socket.bind(("127.0.0.1", 0))
        self._tcp_socket.listen(5)
        self._tcp_thread = threading.Thread(target=self._handle_tcp, daemon=True)
        self._tcp_thread.start()
        self._http_server = HTTPServer(("127.0.0.1", 0), self._create_http_handler())
        self._http_thread = threading.Thread(target=self._handle_http, daemon=True)
        self._http_thread.start()


def main():
    cfg = SimulatorConfig(
        sample_rate_hz=int(os.environ.get("COF_RATE_HZ", "1000")),
        seed=1,
        signal_frequency_hz=0.0,
        noise_stddev=0,
        signal_amplitude=100000,
        counts_per_force=1000000,
        counts_per_torque=1000000,
        # cof_tester's own fault injection (COF_LOSS, COF_REORDER: probabilities).
        faults=FaultConfig(
            loss_probability=float(os.environ.get("COF_LOSS", "0")),
            reorder_probability=float(os.environ.get("COF_REORDER", "0")),
        ),
    )
    sim = LoopbackSimulator(cfg)
    sim.start()
    print(
        json.dumps(
            {
                "udp": sim._udp_socket.getsockname()[1],
                "tcp": sim._tcp_socket.getsockname()[1],
                "http": sim._http_server.server_address[1],
            }
        ),
        flush=True,
    )
    sys.stdin.read()
    sim.stop()


if __name__ == "__main__":
    main()
