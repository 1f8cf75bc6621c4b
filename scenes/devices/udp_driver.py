#!/usr/bin/env python3
"""Fake haptic device driver for cosurg's UDP bridge (see docs/haptics.md).

Sends pose datagrams at ~1 kHz (a tool tip moving on a small circle that dips 3 mm down
along -z) to the bridge and reads the force datagrams it sends back. A real driver
replaces `tip_at` with the device's reading and calls its force command with `force`.

    python3 scenes/devices/udp_driver.py --addr 127.0.0.1:7701 --seconds 3
"""
import argparse
import math
import socket
import struct
import time

POSE = struct.Struct("<4sIQ3d4ddI")  # 84 bytes, device -> cosurg
FORCE = struct.Struct("<4sIIIQ3d3d")  # 72 bytes, cosurg -> device
assert POSE.size == 84 and FORCE.size == 72
FLAG_STALE = 1


def tip_at(t):
    """Tip position (m), orientation quaternion (w, x, y, z), jaw (rad), buttons."""
    x = 0.01 * math.cos(2 * math.pi * 0.5 * t)
    y = 0.01 * math.sin(2 * math.pi * 0.5 * t)
    z = -0.003 * (0.5 - 0.5 * math.cos(2 * math.pi * 0.25 * t))
    return (x, y, z), (1.0, 0.0, 0.0, 0.0), 0.3, 0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addr", default="127.0.0.1:7701", help="cosurg bridge host:port")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--rate", type=float, default=1000.0, help="pose datagrams per second")
    a = ap.parse_args()
    host, port = a.addr.rsplit(":", 1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect((host, int(port)))
    sock.setblocking(False)

    start = time.monotonic()
    seq, received, stale, fmax, rtts = 0, 0, 0, 0.0, []
    next_send = start
    while time.monotonic() - start < a.seconds:
        now = time.monotonic()
        if now >= next_send:
            seq = (seq + 1) & 0xFFFFFFFF
            device_us = int((now - start) * 1e6)
            pos, quat, jaw, buttons = tip_at(now - start)
            sock.send(POSE.pack(b"CSGP", seq, device_us, *pos, *quat, jaw, buttons))
            next_send += 1.0 / a.rate
        try:
            while True:
                data = sock.recv(256)
                if len(data) < FORCE.size or data[:4] != b"CSGF":
                    continue
                _, fseq, echo_seq, flags, echo_us, fx, fy, fz, tx, ty, tz = FORCE.unpack(data[:72])
                received += 1
                stale += bool(flags & FLAG_STALE)
                fmax = max(fmax, math.sqrt(fx * fx + fy * fy + fz * fz))
                if echo_seq:
                    rtts.append((time.monotonic() - start) * 1e6 - echo_us)
                # a real driver: device.set_force(fx, fy, fz) here
        except (BlockingIOError, ConnectionRefusedError):
            pass
        time.sleep(0.0002)
    rtts.sort()
    p50 = rtts[len(rtts) // 2] if rtts else float("nan")
    print(f"sent {seq} poses, received {received} forces ({stale} flagged stale), "
          f"max |F| {fmax:.3f} N, pose->force age p50 {p50:.0f} us")


if __name__ == "__main__":
    main()
