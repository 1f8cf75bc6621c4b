//! `UdpBridgeDevice`: a haptic device driven by another process over UDP, so that real
//! device drivers (OpenHaptics, CHAI3D, libnifalcon, …) plug in without linking into
//! cosurg. The format is documented in `docs/haptics.md`; all fields little-endian.
//!
//! Device → cosurg, [`PoseDatagram`], 84 bytes:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `b"CSGP"` |
//! | 4 | 4 | `u32` sequence number (+1 per datagram, wrapping) |
//! | 8 | 8 | `u64` device timestamp, µs (any epoch; echoed back) |
//! | 16 | 24 | `f64` ×3 tip position, m (scene frame) |
//! | 40 | 32 | `f64` ×4 orientation quaternion w, x, y, z (normalised on receipt) |
//! | 72 | 8 | `f64` jaw opening angle, rad |
//! | 80 | 4 | `u32` buttons, bit i = button i |
//!
//! cosurg → device, [`ForceDatagram`], 72 bytes, one per haptic tick once the device's
//! address is known:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `b"CSGF"` |
//! | 4 | 4 | `u32` sequence number of this datagram |
//! | 8 | 4 | `u32` echo: sequence number of the newest pose datagram received |
//! | 12 | 4 | `u32` flags: bit 0 = device input stale (force fading out) |
//! | 16 | 8 | `u64` echo: device timestamp of that pose datagram, µs |
//! | 24 | 24 | `f64` ×3 force on the tool, N |
//! | 48 | 24 | `f64` ×3 torque, N·m |

use std::net::{SocketAddr, ToSocketAddrs, UdpSocket};
use std::time::{Duration, Instant};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::{HapticDevice, HapticError, ToolInput};

/// Magic of pose datagrams (device → cosurg).
pub const POSE_MAGIC: [u8; 4] = *b"CSGP";
/// Magic of force datagrams (cosurg → device).
pub const FORCE_MAGIC: [u8; 4] = *b"CSGF";
/// Size of a pose datagram, bytes.
pub const POSE_LEN: usize = 84;
/// Size of a force datagram, bytes.
pub const FORCE_LEN: usize = 72;
/// Default time without pose datagrams after which the input is stale.
pub const DEFAULT_STALE_AFTER: Duration = Duration::from_millis(50);
/// Flag bit of [`ForceDatagram::flags`]: the device input is stale.
pub const FLAG_STALE: u32 = 1;

/// A pose datagram (device → cosurg).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseDatagram {
    /// Sequence number (+1 per datagram, wrapping).
    pub seq: u32,
    /// Device timestamp, µs.
    pub device_time_us: u64,
    /// Tip position, m.
    pub position: [f64; 3],
    /// Orientation quaternion `[w, x, y, z]`.
    pub orientation: [f64; 4],
    /// Jaw angle, rad.
    pub jaw: f64,
    /// Buttons bit set.
    pub buttons: u32,
}

/// A force datagram (cosurg → device).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForceDatagram {
    /// Sequence number of this datagram.
    pub seq: u32,
    /// Sequence number of the newest pose received.
    pub echo_seq: u32,
    /// Flags ([`FLAG_STALE`]).
    pub flags: u32,
    /// Device timestamp of the newest pose received, µs.
    pub echo_device_time_us: u64,
    /// Force, N.
    pub force: [f64; 3],
    /// Torque, N·m.
    pub torque: [f64; 3],
}

fn put_f64s(out: &mut [u8], at: usize, v: &[f64]) {
    for (i, x) in v.iter().enumerate() {
        out[at + 8 * i..at + 8 * i + 8].copy_from_slice(&x.to_le_bytes());
    }
}

fn get_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

fn get_u64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

fn get_f64s<const N: usize>(b: &[u8], at: usize) -> [f64; N] {
    std::array::from_fn(|i| f64::from_bits(get_u64(b, at + 8 * i)))
}

impl PoseDatagram {
    /// Encodes the datagram.
    pub fn encode(&self) -> [u8; POSE_LEN] {
        let mut b = [0u8; POSE_LEN];
        b[0..4].copy_from_slice(&POSE_MAGIC);
        b[4..8].copy_from_slice(&self.seq.to_le_bytes());
        b[8..16].copy_from_slice(&self.device_time_us.to_le_bytes());
        put_f64s(&mut b, 16, &self.position);
        put_f64s(&mut b, 40, &self.orientation);
        put_f64s(&mut b, 72, &[self.jaw]);
        b[80..84].copy_from_slice(&self.buttons.to_le_bytes());
        b
    }

    /// Decodes a datagram: `None` for a wrong length or magic (longer datagrams are
    /// accepted; extra bytes are reserved for later versions).
    pub fn decode(b: &[u8]) -> Option<Self> {
        if b.len() < POSE_LEN || b[0..4] != POSE_MAGIC {
            return None;
        }
        Some(PoseDatagram {
            seq: get_u32(b, 4),
            device_time_us: get_u64(b, 8),
            position: get_f64s(b, 16),
            orientation: get_f64s(b, 40),
            jaw: f64::from_bits(get_u64(b, 72)),
            buttons: get_u32(b, 80),
        })
    }
}

impl ForceDatagram {
    /// Encodes the datagram.
    pub fn encode(&self) -> [u8; FORCE_LEN] {
        let mut b = [0u8; FORCE_LEN];
        b[0..4].copy_from_slice(&FORCE_MAGIC);
        b[4..8].copy_from_slice(&self.seq.to_le_bytes());
        b[8..12].copy_from_slice(&self.echo_seq.to_le_bytes());
        b[12..16].copy_from_slice(&self.flags.to_le_bytes());
        b[16..24].copy_from_slice(&self.echo_device_time_us.to_le_bytes());
        put_f64s(&mut b, 24, &self.force);
        put_f64s(&mut b, 48, &self.torque);
        b
    }

    /// Decodes a datagram (`None` for a wrong length or magic).
    pub fn decode(b: &[u8]) -> Option<Self> {
        if b.len() < FORCE_LEN || b[0..4] != FORCE_MAGIC {
            return None;
        }
        Some(ForceDatagram {
            seq: get_u32(b, 4),
            echo_seq: get_u32(b, 8),
            flags: get_u32(b, 12),
            echo_device_time_us: get_u64(b, 16),
            force: get_f64s(b, 24),
            torque: get_f64s(b, 48),
        })
    }
}

/// Counters of a [`UdpBridgeDevice`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct UdpBridgeStats {
    /// Pose datagrams accepted.
    pub received: u64,
    /// Datagrams with a wrong size, magic or non-finite values.
    pub malformed: u64,
    /// Pose datagrams older than the newest accepted one (dropped).
    pub out_of_order: u64,
    /// Force datagrams sent.
    pub sent: u64,
    /// Force datagrams the OS refused.
    pub send_errors: u64,
    /// Times the input went from fresh to stale.
    pub stale_events: u64,
    /// Reads that found the input stale (including before the first datagram).
    pub stale_reads: u64,
}

/// A device on the other end of a UDP socket (see the module docs for the format).
/// Forces go to the address of the newest pose datagram unless a fixed peer is set.
pub struct UdpBridgeDevice {
    socket: UdpSocket,
    name: String,
    peer: Option<SocketAddr>,
    fixed_peer: bool,
    stale_after: Duration,
    last: ToolInput,
    last_seq: Option<u32>,
    last_device_time_us: u64,
    last_rx: Option<Instant>,
    stale: bool,
    tx_seq: u32,
    stats: UdpBridgeStats,
}

impl std::fmt::Debug for UdpBridgeDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UdpBridgeDevice")
            .field("name", &self.name)
            .field("peer", &self.peer)
            .field("stats", &self.stats)
            .finish()
    }
}

impl UdpBridgeDevice {
    /// Binds a non-blocking UDP socket at `addr` (e.g. `127.0.0.1:7701`; port 0: any).
    pub fn bind(addr: impl ToSocketAddrs) -> Result<Self, HapticError> {
        let socket = UdpSocket::bind(addr)
            .map_err(|e| HapticError::io("binding the haptic UDP bridge", e))?;
        socket
            .set_nonblocking(true)
            .map_err(|e| HapticError::io("haptic UDP bridge: non-blocking mode", e))?;
        let local = socket
            .local_addr()
            .map_err(|e| HapticError::io("haptic UDP bridge: local address", e))?;
        Ok(UdpBridgeDevice {
            socket,
            name: format!("udp:{local}"),
            peer: None,
            fixed_peer: false,
            stale_after: DEFAULT_STALE_AFTER,
            last: ToolInput::default(),
            last_seq: None,
            last_device_time_us: 0,
            last_rx: None,
            stale: true,
            tx_seq: 0,
            stats: UdpBridgeStats::default(),
        })
    }

    /// Sends forces to `peer` always (instead of the sender of the newest pose).
    pub fn with_peer(mut self, peer: SocketAddr) -> Self {
        self.peer = Some(peer);
        self.fixed_peer = true;
        self
    }

    /// Input older than `d` is stale (default 50 ms).
    pub fn with_stale_after(mut self, d: Duration) -> Self {
        self.stale_after = d;
        self
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.socket
            .local_addr()
            .expect("bound socket has an address")
    }

    /// Counters.
    pub fn stats(&self) -> UdpBridgeStats {
        self.stats
    }

    /// Device timestamp of the newest accepted pose, µs.
    pub fn last_device_time_us(&self) -> u64 {
        self.last_device_time_us
    }

    fn accept(&mut self, d: &PoseDatagram, from: SocketAddr, t: Duration, now: Instant) {
        let finite = d
            .position
            .iter()
            .chain(&d.orientation)
            .all(|v| v.is_finite())
            && d.jaw.is_finite();
        let q = Quaternion::new(
            d.orientation[0],
            d.orientation[1],
            d.orientation[2],
            d.orientation[3],
        );
        if !finite || q.norm() < 1e-9 {
            self.stats.malformed += 1;
            return;
        }
        if let Some(prev) = self.last_seq
            && (d.seq.wrapping_sub(prev) as i32) <= 0
            && !self.stale
        {
            // Older or duplicate; while stale, any sequence is accepted (driver restart).
            self.stats.out_of_order += 1;
            return;
        }
        self.last_seq = Some(d.seq);
        self.last_device_time_us = d.device_time_us;
        self.last_rx = Some(now);
        self.stale = false;
        if !self.fixed_peer {
            self.peer = Some(from);
        }
        self.last = ToolInput {
            time: t,
            position: Vector3::from(d.position),
            orientation: UnitQuaternion::from_quaternion(q),
            jaw: d.jaw,
            buttons: d.buttons,
        };
        self.stats.received += 1;
    }
}

impl HapticDevice for UdpBridgeDevice {
    fn read(&mut self, t: Duration) -> ToolInput {
        let mut buf = [0u8; 512];
        loop {
            match self.socket.recv_from(&mut buf) {
                Ok((n, from)) => match PoseDatagram::decode(&buf[..n]) {
                    Some(d) => self.accept(&d, from, t, Instant::now()),
                    _ => self.stats.malformed += 1,
                },
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                // e.g. ECONNREFUSED from an earlier send: not fatal, try next tick.
                Err(_) => break,
            }
        }
        let fresh = self
            .last_rx
            .is_some_and(|r| r.elapsed() <= self.stale_after);
        if !fresh {
            if !self.stale {
                self.stats.stale_events += 1;
                tracing::warn!(device = %self.name, "haptic device input stale: fading force out");
            }
            self.stale = true;
            self.stats.stale_reads += 1;
        }
        // The pose is the newest received (held while stale); its time is this read.
        self.last.time = t;
        self.last
    }

    fn apply(&mut self, force: Vector3<f64>, torque: Vector3<f64>) {
        let Some(peer) = self.peer else { return };
        let d = ForceDatagram {
            seq: self.tx_seq,
            echo_seq: self.last_seq.unwrap_or(0),
            flags: if self.stale { FLAG_STALE } else { 0 },
            echo_device_time_us: self.last_device_time_us,
            force: force.into(),
            torque: torque.into(),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        match self.socket.send_to(&d.encode(), peer) {
            Ok(_) => self.stats.sent += 1,
            Err(_) => self.stats.send_errors += 1,
        }
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn input_stale(&self) -> bool {
        self.stale
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn datagrams_roundtrip_and_layout() {
        let p = PoseDatagram {
            seq: 0xDEAD_BEEF,
            device_time_us: 123_456_789,
            position: [0.01, -0.02, 0.03],
            orientation: [1.0, 0.0, 0.0, 0.0],
            jaw: 0.5,
            buttons: 0b101,
        };
        let b = p.encode();
        assert_eq!(&b[0..4], b"CSGP");
        assert_eq!(&b[4..8], &[0xEF, 0xBE, 0xAD, 0xDE], "little-endian");
        assert_eq!(&b[16..24], &0.01f64.to_le_bytes());
        assert_eq!(PoseDatagram::decode(&b), Some(p));
        assert_eq!(PoseDatagram::decode(&b[..83]), None);
        let f = ForceDatagram {
            seq: 7,
            echo_seq: 0xDEAD_BEEF,
            flags: FLAG_STALE,
            echo_device_time_us: 123_456_789,
            force: [1.0, 2.0, 3.0],
            torque: [0.0, 0.1, 0.0],
        };
        let b = f.encode();
        assert_eq!(&b[0..4], b"CSGF");
        assert_eq!(&b[24..32], &1.0f64.to_le_bytes());
        assert_eq!(ForceDatagram::decode(&b), Some(f));
        assert_eq!(ForceDatagram::decode(&p.encode()), None, "wrong magic");
    }
}
