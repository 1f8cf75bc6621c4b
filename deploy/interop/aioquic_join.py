#!/usr/bin/env python3
"""Interop check: a Python aioquic client against cosurg-server.

It completes a QUIC + TLS 1.3 handshake (ALPN ``cosurg/1``), authenticates the coordinator
either by pinning its certificate fingerprint (``--pin``: SHA-256 of the DER certificate,
checked right after the handshake and before any application data is sent; aioquic itself
still verifies the handshake signature against the certificate's key) or with the
coordinator's PEM as CA (``--ca``), opens the session-control stream and sends a hand-encoded
first frame:

* ``--mode garbage``     a well-framed but undecodable message -> Refusal ``Malformed``,
                         connection closed with application error 8 (MALFORMED);
* ``--mode wrong-token`` a correct ``Join`` with a wrong token -> Refusal ``WrongToken``,
                         application error 1 (WRONG_TOKEN);
* ``--mode join``        a correct ``Join`` (with ``--invite INVITATION`` for a trainee or
                         observer, from ``cosurg-server invite``) -> ``Welcome``; then one coordinator heartbeat
                         datagram is awaited and one is sent (datagrams are only negotiated
                         because the client sets ``max_datagram_frame_size``), then ``Leave``
                         -> closed with application error 0 (NORMAL).

Wire format (see ``proto/src/codec.rs``): a stream frame is a 4-byte big-endian length and
the message; a message is the wire tag byte (the protocol version, 9) followed by the postcard
encoding of ``proto::Message`` (enum variant index as varint, integers as LEB128 varints,
strings as varint length + UTF-8). ``--print-join-hex`` prints an encoded Join frame without
touching the network (the Rust test compares it with ``proto::encode_frame``).

Output: ``key: value`` lines and a final ``RESULT: PASS`` / ``RESULT: FAIL ...`` (exit 0 / 1).
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import ssl
import struct
import sys
import time

WIRE_TAG = 9
PROTOCOL_VERSION = 9
# proto::TIME_SCALE_REAL_MILLI: a session in real time.
TIME_SCALE_REAL_MILLI = 1000
ALPN = "cosurg/1"

# proto::Message variant indices (append-only within a protocol version).
MSG = {
    "Join": 0, "Welcome": 1, "Refusal": 2, "ClockPing": 3, "ClockPong": 4, "SimTime": 5,
    "ToolPose": 6, "Keyframe": 7, "TreeDelta": 8, "KeyframeAck": 9, "OwnershipRequest": 10,
    "OwnershipGrant": 11, "OwnershipRelease": 12, "OwnershipDeny": 13, "Snapshot": 14,
    "Teaching": 15, "Command": 16, "Leave": 17, "Heartbeat": 18, "Status": 19,
    "SiteJoined": 20, "Admin": 21, "Invitation": 22, "CommandRefused": 23,
    "SessionCreated": 24, "Topology": 25, "ToolPoseHistory": 26,
}
MSG_NAME = {v: k for k, v in MSG.items()}
ROLES = ["instructor", "trainee", "observer"]
REFUSAL_REASONS = ["WrongToken", "WrongVersion", "WrongScene", "WrongSession", "NameTaken",
                   "Full", "Kicked", "Malformed", "InvalidInvitation", "InvitationExpired",
                   "InvitationRevoked", "WrongRole", "WrongSite", "RateLimited",
                   "WrongTimeScale"]
# proto::close_code
CLOSE_CODES = {0: "NORMAL", 1: "WRONG_TOKEN", 2: "WRONG_VERSION", 3: "WRONG_SCENE",
               4: "WRONG_SESSION", 5: "NAME_TAKEN", 6: "FULL", 7: "KICKED", 8: "MALFORMED",
               9: "PROTOCOL_ERROR", 10: "JOIN_TIMEOUT", 11: "OVERLOADED", 12: "TIMED_OUT",
               13: "INVALID_INVITATION", 14: "INVITATION_EXPIRED", 15: "INVITATION_REVOKED",
               16: "WRONG_ROLE", 17: "WRONG_SITE", 18: "RATE_LIMITED", 19: "WRONG_TIME_SCALE"}


# ---------------------------------------------------------------- postcard encoding ----
def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def pstr(s: str) -> bytes:
    b = s.encode("utf-8")
    return varint(len(b)) + b


def message(variant: str, body: bytes) -> bytes:
    return bytes([WIRE_TAG]) + varint(MSG[variant]) + body


def frame(msg: bytes) -> bytes:
    return struct.pack(">I", len(msg)) + msg


def join_frame(site: str, role: str, session: str, token: str, scene_hash: str,
               version: int = PROTOCOL_VERSION, invite: str | None = None) -> bytes:
    # struct Join { protocol_version: u16, scene_hash: String, role: Role, site_name: String,
    #               session: String, credential: Credential, time_scale_milli: u32 }
    # enum Credential { Token(String), Invitation(String) }
    credential = varint(1) + pstr(invite) if invite else varint(0) + pstr(token)
    body = (varint(version) + pstr(scene_hash) + varint(ROLES.index(role)) + pstr(site)
            + pstr(session) + credential + varint(TIME_SCALE_REAL_MILLI))
    return frame(message("Join", body))


class Reader:
    def __init__(self, data: bytes):
        self.data = data
        self.pos = 0

    def byte(self) -> int:
        if self.pos >= len(self.data):
            raise ValueError("message ends early")
        b = self.data[self.pos]
        self.pos += 1
        return b

    def varint(self) -> int:
        n = shift = 0
        while True:
            b = self.byte()
            n |= (b & 0x7F) << shift
            if not b & 0x80:
                return n
            shift += 7
            if shift > 70:
                raise ValueError("varint too long")

    def string(self) -> str:
        n = self.varint()
        if self.pos + n > len(self.data):
            raise ValueError("string ends early")
        s = self.data[self.pos:self.pos + n].decode("utf-8")
        self.pos += n
        return s


def decode(msg: bytes) -> tuple[str, dict]:
    """Decode the messages this client needs; others are returned by name only."""
    r = Reader(msg)
    tag = r.byte()
    if tag != WIRE_TAG:
        raise ValueError(f"wire tag {tag}, expected {WIRE_TAG}")
    variant = r.varint()
    name = MSG_NAME.get(variant, f"unknown({variant})")
    if name == "Refusal":
        idx = r.varint()
        reason = REFUSAL_REASONS[idx] if idx < len(REFUSAL_REASONS) else f"unknown({idx})"
        detail = {}
        if reason == "WrongVersion":
            detail = {"server": r.varint(), "client": r.varint()}
        elif reason == "WrongScene":
            detail = {"expected": r.string()}
        elif reason == "RateLimited":
            detail = {"retry_after_ms": r.varint()}
        elif reason == "WrongTimeScale":
            detail = {"server_milli": r.varint(), "client_milli": r.varint()}
        return name, {"reason": reason, **detail, "text": r.string()}
    if name == "Welcome":
        site = r.varint()
        info = {"name": r.string(), "scene_hash": r.string(), "max_sites": r.varint(),
                "protocol_version": r.varint(), "heartbeat_interval_us": r.varint()}
        sites = []
        for _ in range(r.varint()):
            sites.append({"site": r.varint(), "name": r.string(), "role": ROLES[r.varint()]})
        return name, {"site": site, "session": info, "sites": sites,
                      "coordinator_time_us": r.varint()}
    if name == "Heartbeat":
        return name, {"site": r.varint(), "time_us": r.varint()}
    return name, {}


class FrameBuffer:
    def __init__(self):
        self.buf = b""

    def push(self, data: bytes) -> list[bytes]:
        self.buf += data
        out = []
        while len(self.buf) >= 4:
            (n,) = struct.unpack(">I", self.buf[:4])
            if len(self.buf) < 4 + n:
                break
            out.append(self.buf[4:4 + n])
            self.buf = self.buf[4 + n:]
        return out


def fingerprint_of(der: bytes) -> str:
    return ":".join(f"{b:02X}" for b in hashlib.sha256(der).digest())


def normalise_fp(fp: str) -> str:
    clean = "".join(c for c in fp if c not in ": -").upper()
    return ":".join(clean[i:i + 2] for i in range(0, len(clean), 2))


# ---------------------------------------------------------------- the client -----------
async def run(args) -> int:
    from aioquic.asyncio import connect
    from aioquic.asyncio.protocol import QuicConnectionProtocol
    from aioquic.quic import events
    from aioquic.quic.configuration import QuicConfiguration
    from cryptography.hazmat.primitives.serialization import Encoding

    def out(key, value):
        print(f"{key}: {value}", flush=True)

    class Client(QuicConnectionProtocol):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            self.frames: asyncio.Queue = asyncio.Queue()
            self.datagrams: asyncio.Queue = asyncio.Queue()
            self.closed = asyncio.get_running_loop().create_future()
            self.control = FrameBuffer()
            self.control_id = None
            self.uni_streams = set()

        def quic_event_received(self, ev):
            if isinstance(ev, events.StreamDataReceived):
                if ev.stream_id == self.control_id:
                    for f in self.control.push(ev.data):
                        self.frames.put_nowait(f)
                else:
                    self.uni_streams.add(ev.stream_id)
            elif isinstance(ev, events.DatagramFrameReceived):
                self.datagrams.put_nowait(ev.data)
            elif isinstance(ev, events.ConnectionTerminated):
                if not self.closed.done():
                    self.closed.set_result(ev)

    config = QuicConfiguration(
        is_client=True,
        alpn_protocols=[ALPN],
        server_name=args.server_name,
        # Without this aioquic does not offer the DATAGRAM extension (RFC 9221) and the
        # coordinator's datagrams (heartbeats, clock, poses) cannot flow.
        max_datagram_frame_size=65536,
        idle_timeout=15.0,
    )
    if args.ca:
        config.verify_mode = ssl.CERT_REQUIRED
        config.load_verify_locations(cafile=args.ca)
        out("trust", f"CA {args.ca} (server name {args.server_name})")
    else:
        # Pinning: no chain validation by aioquic, exact certificate checked below before any
        # application data is sent.
        config.verify_mode = ssl.CERT_NONE
        out("trust", f"pinned fingerprint {normalise_fp(args.pin)}")

    t0 = time.monotonic()
    async with connect(args.host, args.port, configuration=config, create_protocol=Client,
                       wait_connected=True) as client:
        quic = client._quic
        tls = quic.tls
        out("handshake", f"complete in {1000 * (time.monotonic() - t0):.1f} ms")
        out("tls_version", "TLS 1.3")  # aioquic implements TLS 1.3 only (RFC 9001)
        out("cipher_suite", tls.key_schedule.cipher_suite.name)
        out("alpn", tls.alpn_negotiated)
        cert = tls._peer_certificate
        fp = fingerprint_of(cert.public_bytes(Encoding.DER))
        out("server_certificate", cert.subject.rfc4514_string())
        out("server_fingerprint", fp)
        remote_dg = quic._remote_max_datagram_frame_size
        out("datagrams", f"negotiated (peer max_datagram_frame_size {remote_dg})"
            if remote_dg else "NOT negotiated")
        if tls.alpn_negotiated != ALPN:
            out("RESULT", f"FAIL alpn {tls.alpn_negotiated!r}")
            return 1
        if not args.ca and fp != normalise_fp(args.pin):
            client.close(error_code=0x0100, reason_phrase="certificate pin mismatch")
            out("RESULT", "FAIL certificate fingerprint does not match the pin")
            return 1

        sid = quic.get_next_available_stream_id(is_unidirectional=False)
        client.control_id = sid
        if args.mode == "garbage":
            first = frame(bytes([WIRE_TAG]) + b"\xf7\xff\xff\xff\x0fnot a cosurg message")
            expect = ("Malformed", 8)
        else:
            token = args.token if args.mode == "join" else args.token + "-wrong"
            invite = args.invite if args.mode == "join" else None
            first = join_frame(args.site, args.role, args.session, token, args.scene_hash,
                               invite=invite)
            expect = ("WrongToken", 1) if args.mode == "wrong-token" else (None, 0)
        out("sent", f"{args.mode} frame on control stream {sid} ({len(first)} bytes): "
            f"{first.hex()}")
        quic.send_stream_data(sid, first, end_stream=False)
        client.transmit()

        reply = await asyncio.wait_for(client.frames.get(), args.timeout)
        name, fields = decode(reply)
        out("received", f"{name} {fields}")
        if expect[0] is not None:
            if name != "Refusal" or fields.get("reason") != expect[0]:
                out("RESULT", f"FAIL expected Refusal {expect[0]}, got {name} {fields}")
                return 1
        else:
            if name != "Welcome":
                out("RESULT", f"FAIL expected Welcome, got {name} {fields}")
                return 1
            site = fields["site"]
            dg = await asyncio.wait_for(client.datagrams.get(), args.timeout)
            out("datagram_received", "%s %s" % decode(dg))
            hb = message("Heartbeat", varint(site) + varint(int(time.time() * 1e6)))
            quic.send_datagram_frame(hb)
            out("datagram_sent", f"Heartbeat ({len(hb)} bytes)")
            leave = frame(message("Leave", varint(site) + pstr("aioquic interop done")))
            quic.send_stream_data(sid, leave, end_stream=True)
            client.transmit()
            out("sent", "Leave")

        ev = await asyncio.wait_for(asyncio.shield(client.closed), args.timeout)
        kind = "application" if ev.frame_type is None else f"transport (frame {ev.frame_type})"
        out("connection_close", f"{kind} error code {ev.error_code} "
            f"({CLOSE_CODES.get(ev.error_code, '?')}) reason {ev.reason_phrase!r}")
        if ev.frame_type is not None or ev.error_code != expect[1]:
            out("RESULT", f"FAIL expected application close code {expect[1]}")
            return 1
        if args.mode == "garbage" and "Join" not in ev.reason_phrase:
            out("RESULT", "FAIL close reason does not explain the bad Join")
            return 1
    out("RESULT", f"PASS mode={args.mode}")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=4433)
    p.add_argument("--server-name", default="localhost", help="TLS server name (SNI)")
    trust = p.add_mutually_exclusive_group()
    trust.add_argument("--pin", help="coordinator certificate SHA-256 fingerprint (AB:CD:...)")
    trust.add_argument("--ca", help="PEM file to verify the coordinator certificate with")
    p.add_argument("--mode", choices=["garbage", "wrong-token", "join"], default="garbage")
    p.add_argument("--session", default="interop")
    p.add_argument("--token", default="interop-token")
    p.add_argument("--invite", help="invitation for --mode join (trainee or observer)")
    p.add_argument("--site", default="aioquic")
    p.add_argument("--role", choices=ROLES, default="observer")
    p.add_argument("--scene-hash", default="00" * 32)
    p.add_argument("--timeout", type=float, default=10.0)
    p.add_argument("--print-join-hex", action="store_true",
                   help="print the encoded Join frame (no network) and exit")
    args = p.parse_args()
    if args.print_join_hex:
        print(join_frame(args.site, args.role, args.session, args.token, args.scene_hash,
                         invite=args.invite).hex())
        return 0
    if not args.pin and not args.ca:
        p.error("one of --pin or --ca is required")
    try:
        return asyncio.run(asyncio.wait_for(run(args), 4 * args.timeout))
    except ImportError as e:
        print(f"skipped: aioquic not installed ({e})")
        return 2
    except Exception as e:  # noqa: BLE001 - report any failure as a result line
        print(f"RESULT: FAIL {type(e).__name__}: {e}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
