//! Codec: version tag + postcard; length-prefixed framing for streams; datagram budget.
//!
//! * A message is `[WIRE_TAG] ++ postcard(Message)`. [`decode`] never panics on any input and
//!   rejects unknown tags, postcard errors and trailing bytes.
//! * On streams each message is a frame: a 4-byte big-endian length `n` followed by `n` bytes
//!   of encoded message. [`FrameDecoder`] accepts arbitrary chunks, enforces a maximum frame
//!   size (checked as soon as the header arrives, before buffering the body) and reports a
//!   truncated final frame via [`FrameDecoder::finish`].
//! * Datagrams carry exactly one encoded message, no length prefix; [`encode_datagram`]
//!   checks it fits the budget ([`DEFAULT_DATAGRAM_BUDGET`] = 1100 bytes, below quinn's
//!   ≈ 1162-byte `max_datagram_size()` at a 1200-byte MTU).

use crate::msg::Message;

/// First byte of every encoded message. Equal to the low byte of
/// [`crate::PROTOCOL_VERSION`].
pub const WIRE_TAG: u8 = crate::PROTOCOL_VERSION as u8;
/// Length of the frame header.
pub const FRAME_HEADER_LEN: usize = 4;
/// Default maximum frame body size: 8 MiB (a snapshot of many keyframes fits).
pub const DEFAULT_MAX_FRAME: usize = 8 << 20;
/// Default datagram payload budget (bytes).
pub const DEFAULT_DATAGRAM_BUDGET: usize = 1100;

/// Decoding failure of one message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("empty message")]
    Empty,
    #[error("unknown wire version tag {got} (this build speaks {WIRE_TAG})")]
    UnknownVersion { got: u8 },
    #[error("malformed message: {0}")]
    Malformed(#[from] postcard::Error),
    #[error("{0} trailing bytes after message")]
    TrailingBytes(usize),
}

/// Encode a message: version tag + postcard.
pub fn encode(msg: &Message) -> Vec<u8> {
    let mut out = vec![WIRE_TAG];
    // Serialising into a Vec cannot fail for these types (no maps with non-string keys,
    // no unsupported serde features); treat a failure as a bug.
    let body = postcard::to_extend(msg, out).expect("postcard serialisation of Message");
    out = body;
    out
}

/// Decode a message produced by [`encode`]. Never panics.
pub fn decode(bytes: &[u8]) -> Result<Message, DecodeError> {
    let (&tag, body) = bytes.split_first().ok_or(DecodeError::Empty)?;
    if tag != WIRE_TAG {
        return Err(DecodeError::UnknownVersion { got: tag });
    }
    let (msg, rest) = postcard::take_from_bytes::<Message>(body)?;
    if !rest.is_empty() {
        return Err(DecodeError::TrailingBytes(rest.len()));
    }
    Ok(msg)
}

/// Encode a message as one stream frame (length prefix + encoded message).
pub fn encode_frame(msg: &Message) -> Vec<u8> {
    let body = encode(msg);
    let mut out = Vec::with_capacity(FRAME_HEADER_LEN + body.len());
    out.extend_from_slice(&(body.len() as u32).to_be_bytes());
    out.extend_from_slice(&body);
    out
}

/// Stream framing failure.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("frame of {len} bytes exceeds the maximum of {max} bytes")]
    Oversize { len: usize, max: usize },
    #[error("stream ended inside a frame: {have} of {need} bytes received")]
    Truncated { have: usize, need: usize },
    #[error("zero-length frame")]
    Empty,
    #[error(transparent)]
    Decode(#[from] DecodeError),
}

/// Incremental decoder of length-prefixed frames.
///
/// Feed bytes with [`push`](Self::push) in any chunking, then pull complete frames with
/// [`next_frame`](Self::next_frame) / [`next_message`](Self::next_message) until `None`.
/// After an error the decoder is poisoned (the stream cannot be resynchronised) and returns
/// the same error again.
#[derive(Debug)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    start: usize,
    max_frame: usize,
    error: Option<FrameError>,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new(DEFAULT_MAX_FRAME)
    }
}

impl FrameDecoder {
    /// New decoder rejecting frames whose body exceeds `max_frame` bytes.
    pub fn new(max_frame: usize) -> Self {
        Self {
            buf: Vec::new(),
            start: 0,
            max_frame,
            error: None,
        }
    }

    /// The maximum frame body size.
    pub fn max_frame(&self) -> usize {
        self.max_frame
    }

    /// Change the maximum frame body size (e.g. raise it once a peer has authenticated).
    /// Frames whose header was already checked are not re-checked.
    pub fn set_max_frame(&mut self, max_frame: usize) {
        self.max_frame = max_frame;
    }

    /// Bytes buffered but not yet returned as frames.
    pub fn buffered(&self) -> usize {
        self.buf.len() - self.start
    }

    /// Append received bytes.
    pub fn push(&mut self, chunk: &[u8]) {
        if self.start > 0 && self.start == self.buf.len() {
            self.buf.clear();
            self.start = 0;
        } else if self.start > 64 * 1024 && self.start * 2 > self.buf.len() {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        self.buf.extend_from_slice(chunk);
    }

    fn pending(&self) -> &[u8] {
        &self.buf[self.start..]
    }

    /// Length of the next frame's body, checking the header once it is complete.
    fn header(&mut self) -> Result<Option<usize>, FrameError> {
        if let Some(e) = &self.error {
            return Err(e.clone());
        }
        let p = self.pending();
        if p.len() < FRAME_HEADER_LEN {
            return Ok(None);
        }
        let len = u32::from_be_bytes([p[0], p[1], p[2], p[3]]) as usize;
        let err = if len > self.max_frame {
            Some(FrameError::Oversize {
                len,
                max: self.max_frame,
            })
        } else if len == 0 {
            Some(FrameError::Empty)
        } else {
            None
        };
        if let Some(e) = err {
            self.error = Some(e.clone());
            return Err(e);
        }
        Ok(Some(len))
    }

    /// Bytes still needed to complete the current frame (at least 1 while waiting for a
    /// header); useful to bound reads.
    pub fn wanted(&mut self) -> usize {
        match self.header() {
            Ok(Some(len)) => (FRAME_HEADER_LEN + len)
                .saturating_sub(self.buffered())
                .max(1),
            Ok(None) => FRAME_HEADER_LEN - self.buffered(),
            Err(_) => 0,
        }
    }

    /// Next complete frame body, if any.
    pub fn next_frame(&mut self) -> Result<Option<Vec<u8>>, FrameError> {
        let Some(len) = self.header()? else {
            return Ok(None);
        };
        if self.buffered() < FRAME_HEADER_LEN + len {
            return Ok(None);
        }
        let s = self.start + FRAME_HEADER_LEN;
        let body = self.buf[s..s + len].to_vec();
        self.start = s + len;
        Ok(Some(body))
    }

    /// Next complete frame decoded as a message. A frame that does not decode is an error
    /// but does not poison the decoder (framing is intact), so a caller may skip it.
    pub fn next_message(&mut self) -> Result<Option<Message>, FrameError> {
        match self.next_frame()? {
            Some(body) => Ok(Some(decode(&body)?)),
            None => Ok(None),
        }
    }

    /// Call at end of stream: an error if a partial frame remains.
    pub fn finish(&mut self) -> Result<(), FrameError> {
        if let Some(e) = &self.error {
            return Err(e.clone());
        }
        let have = self.buffered();
        if have == 0 {
            return Ok(());
        }
        let need = match self.header() {
            Ok(Some(len)) => FRAME_HEADER_LEN + len,
            Ok(None) => FRAME_HEADER_LEN,
            Err(e) => return Err(e),
        };
        Err(FrameError::Truncated { have, need })
    }
}

/// A datagram that does not fit the budget.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{kind} datagram of {size} bytes exceeds the budget of {max} bytes")]
pub struct DatagramTooLarge {
    pub kind: &'static str,
    pub size: usize,
    pub max: usize,
}

/// Encode `msg` for a datagram, checking it fits `max` bytes (use
/// `min(DEFAULT_DATAGRAM_BUDGET, connection.max_datagram_size())`).
pub fn encode_datagram(msg: &Message, max: usize) -> Result<Vec<u8>, DatagramTooLarge> {
    let bytes = encode(msg);
    check_datagram(&bytes, max).map_err(|(size, max)| DatagramTooLarge {
        kind: msg.kind(),
        size,
        max,
    })?;
    Ok(bytes)
}

/// Check an already encoded payload against a datagram budget; `Err((size, max))`.
pub fn check_datagram(payload: &[u8], max: usize) -> Result<(), (usize, usize)> {
    if payload.len() <= max {
        Ok(())
    } else {
        Err((payload.len(), max))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::*;

    fn hb(t: u64) -> Message {
        Message::Heartbeat(Heartbeat {
            site: 3,
            time_us: t,
        })
    }

    #[test]
    fn tag_and_roundtrip() {
        let m = hb(42);
        let b = encode(&m);
        assert_eq!(b[0], WIRE_TAG);
        assert_eq!(decode(&b).unwrap(), m);
    }

    #[test]
    fn decode_errors() {
        assert_eq!(decode(&[]), Err(DecodeError::Empty));
        assert_eq!(
            decode(&[99, 0]),
            Err(DecodeError::UnknownVersion { got: 99 })
        );
        assert!(matches!(
            decode(&[WIRE_TAG]),
            Err(DecodeError::Malformed(_))
        ));
        assert!(matches!(
            decode(&[WIRE_TAG, 200]),
            Err(DecodeError::Malformed(_))
        ));
        let mut b = encode(&hb(1));
        b.push(0);
        assert_eq!(decode(&b), Err(DecodeError::TrailingBytes(1)));
    }

    #[test]
    fn frames_in_any_chunking() {
        let msgs: Vec<Message> = (0..20).map(hb).collect();
        let stream: Vec<u8> = msgs.iter().flat_map(encode_frame).collect();
        for chunk in [1, 2, 3, 5, 7, 64, 4096] {
            let mut d = FrameDecoder::default();
            let mut got = Vec::new();
            for c in stream.chunks(chunk) {
                d.push(c);
                while let Some(m) = d.next_message().unwrap() {
                    got.push(m);
                }
            }
            d.finish().unwrap();
            assert_eq!(got, msgs, "chunk {chunk}");
            assert_eq!(d.buffered(), 0);
        }
    }

    #[test]
    fn oversize_detected_from_header_alone() {
        let mut d = FrameDecoder::new(100);
        d.push(&1000u32.to_be_bytes());
        assert_eq!(
            d.next_frame(),
            Err(FrameError::Oversize {
                len: 1000,
                max: 100
            })
        );
        // poisoned
        d.push(&[0; 10]);
        assert!(d.next_frame().is_err());
        assert!(d.finish().is_err());
    }

    #[test]
    fn zero_length_frame_is_an_error() {
        let mut d = FrameDecoder::default();
        d.push(&[0, 0, 0, 0]);
        assert_eq!(d.next_frame(), Err(FrameError::Empty));
    }

    #[test]
    fn truncated_frames_reported_at_finish() {
        let f = encode_frame(&hb(7));
        for cut in 1..f.len() {
            let mut d = FrameDecoder::default();
            d.push(&f[..cut]);
            assert_eq!(d.next_frame(), Ok(None));
            let need = if cut < FRAME_HEADER_LEN {
                FRAME_HEADER_LEN
            } else {
                f.len()
            };
            assert_eq!(d.finish(), Err(FrameError::Truncated { have: cut, need }));
        }
    }

    #[test]
    fn bad_frame_body_does_not_poison() {
        let mut d = FrameDecoder::default();
        d.push(&[0, 0, 0, 2, WIRE_TAG, 250]);
        d.push(&encode_frame(&hb(5)));
        assert!(matches!(d.next_message(), Err(FrameError::Decode(_))));
        assert_eq!(d.next_message().unwrap(), Some(hb(5)));
    }

    #[test]
    fn wanted_counts_missing_bytes() {
        let f = encode_frame(&hb(7));
        let mut d = FrameDecoder::default();
        assert_eq!(d.wanted(), 4);
        d.push(&f[..2]);
        assert_eq!(d.wanted(), 2);
        d.push(&f[2..5]);
        assert_eq!(d.wanted(), f.len() - 5);
    }

    #[test]
    fn datagram_budget() {
        let small = Message::Heartbeat(Heartbeat {
            site: 1,
            time_us: 2,
        });
        assert!(encode_datagram(&small, DEFAULT_DATAGRAM_BUDGET).is_ok());
        let big = Message::TreeDelta(TreeDelta {
            region: 1,
            site: 1,
            epoch: 0,
            sim_time: 0.0,
            base_keyframe: 1,
            xor_bits: vec![0xAA; 2000],
        });
        let e = encode_datagram(&big, DEFAULT_DATAGRAM_BUDGET).unwrap_err();
        assert_eq!(e.max, 1100);
        assert!(e.size > 2000);
        assert_eq!(e.kind, "tree-delta");
    }

    #[test]
    fn tool_pose_fits_a_datagram_comfortably() {
        let m = Message::ToolPose(ToolPose {
            site: 1,
            tool: 0,
            sim_time_s: 1.0,
            position: [0.1; 3],
            orientation: [1.0, 0.0, 0.0, 0.0],
            jaw_rad: 0.2,
            velocity: [0.0; 3],
            angular_velocity: [0.0; 3],
        });
        assert!(encode(&m).len() < 100);
    }
}
