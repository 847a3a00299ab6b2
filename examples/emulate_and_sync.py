"""Serve a synthetic recording with the emulator and read it as the tracker does: sync the
clock by /time round trips, then map each frame's X-Timestamp to the host clock.

    .venv/bin/python examples/emulate_and_sync.py

Prints, per frame, its number, its capture time on the host clock and how long it took to
arrive. Drives everything through the library (cubecam.emulator, cubecam.mjpeg).
"""

from __future__ import annotations

import http.client
import tempfile
import time
from pathlib import Path

from cubecam import mjpeg
from cubecam.emulator import Emulator, Faults
from cubecam.testdata import CameraSpec, write_recording


def device_time(host: str, port: int) -> tuple[float, float, float]:
    """One /time round trip: (host send, device time, host receive), seconds."""
    conn = http.client.HTTPConnection(host, port, timeout=5)
    sent = time.time()
    conn.request("GET", "/time")
    device = mjpeg.parse_timestamp(conn.getresponse().read().decode())
    received = time.time()
    conn.close()
    return sent, device, received


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        # one camera whose clock runs 100 ppm slow, on a link with 30 ms latency
        rec = write_recording(Path(tmp) / "rec", [CameraSpec("cam1", boot_offset_s=42.0, rate=1 + 100e-6)],
                              frames=40, fps=15.0)
        with Emulator(rec, loop=True, faults=Faults(latency_s=0.03)) as emu:
            host, port = emu.base_urls["cam1"].split("//")[1].strip("/").split(":")
            port = int(port)
            # offset device -> host from the round trip with the shortest delay
            samples = [device_time(host, port) for _ in range(5)]
            sent, device, received = min(samples, key=lambda s: s[2] - s[0])
            offset = (sent + received) / 2 - device
            print(f"clock offset {offset:.3f} s (+-{(received - sent) / 2 * 1000:.1f} ms)")

            conn = http.client.HTTPConnection(host, port, timeout=5)
            conn.request("GET", "/stream")
            response = conn.getresponse()
            for i, part in enumerate(mjpeg.iter_parts(response)):
                arrived = time.time()
                captured = part.timestamp_s + offset
                print(f"frame {part.frame:4d}  captured {captured:.3f}  arrived after "
                      f"{(arrived - captured) * 1000:5.1f} ms")
                if i == 9:
                    break
            conn.close()


if __name__ == "__main__":
    main()
