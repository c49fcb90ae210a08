//! The two ROS wire formats, read and written without copying payloads:
//! ROS 2 CDR (XCDR1 with its 4-byte encapsulation header; fields aligned to their
//! size, relative to the end of that header) and ROS 1 (little-endian, packed,
//! u32 length prefixes).

/// A wire-format read failure: the message ended early or held an impossible value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireError {
    #[error("message ends at byte {len} but {field} needs {need} more bytes")]
    Short {
        field: &'static str,
        need: usize,
        len: usize,
    },
    #[error("unknown CDR encapsulation {0:#06x}")]
    Encapsulation(u16),
    #[error("{field} is not valid UTF-8")]
    Utf8 { field: &'static str },
}

/// Which wire format a reader or writer speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wire {
    /// ROS 2 CDR; `big_endian` from the encapsulation header.
    Cdr { big_endian: bool },
    /// ROS 1 serialization.
    Ros1,
}

/// A cursor over one serialized message.
pub struct WireReader<'a> {
    buf: &'a [u8],
    pos: usize,
    /// Where CDR alignment is measured from (just after the encapsulation header).
    origin: usize,
    wire: Wire,
}

impl<'a> WireReader<'a> {
    /// A CDR reader; consumes and checks the encapsulation header.
    pub fn cdr(buf: &'a [u8]) -> Result<Self, WireError> {
        if buf.len() < 4 {
            return Err(WireError::Short {
                field: "CDR header",
                need: 4,
                len: buf.len(),
            });
        }
        let big_endian = match u16::from_be_bytes([buf[0], buf[1]]) {
            0x0000 | 0x0002 => true,
            0x0001 | 0x0003 => false,
            other => return Err(WireError::Encapsulation(other)),
        };
        Ok(WireReader {
            buf,
            pos: 4,
            origin: 4,
            wire: Wire::Cdr { big_endian },
        })
    }

    pub fn ros1(buf: &'a [u8]) -> Self {
        WireReader {
            buf,
            pos: 0,
            origin: 0,
            wire: Wire::Ros1,
        }
    }

    fn take(&mut self, n: usize, align: usize, field: &'static str) -> Result<&'a [u8], WireError> {
        if let Wire::Cdr { .. } = self.wire {
            let rel = self.pos - self.origin;
            self.pos += (align - rel % align) % align;
        }
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        let Some(end) = end else {
            return Err(WireError::Short {
                field,
                need: n,
                len: self.buf.len(),
            });
        };
        let out = &self.buf[self.pos..end];
        self.pos = end;
        Ok(out)
    }

    fn big_endian(&self) -> bool {
        matches!(self.wire, Wire::Cdr { big_endian: true })
    }

    pub fn u8(&mut self, field: &'static str) -> Result<u8, WireError> {
        Ok(self.take(1, 1, field)?[0])
    }

    pub fn u32(&mut self, field: &'static str) -> Result<u32, WireError> {
        let b: [u8; 4] = self.take(4, 4, field)?.try_into().unwrap_or_default();
        Ok(if self.big_endian() {
            u32::from_be_bytes(b)
        } else {
            u32::from_le_bytes(b)
        })
    }

    pub fn i32(&mut self, field: &'static str) -> Result<i32, WireError> {
        Ok(self.u32(field)? as i32)
    }

    /// A length-prefixed byte sequence, borrowed.
    pub fn bytes(&mut self, field: &'static str) -> Result<&'a [u8], WireError> {
        let n = self.u32(field)? as usize;
        self.take(n, 1, field)
    }

    /// A string (CDR strings carry a NUL terminator inside their length).
    pub fn string(&mut self, field: &'static str) -> Result<&'a str, WireError> {
        let mut b = self.bytes(field)?;
        if let (Wire::Cdr { .. }, [head @ .., 0]) = (self.wire, b) {
            b = head;
        }
        std::str::from_utf8(b).map_err(|_| WireError::Utf8 { field })
    }

    /// The message header's stamp as nanoseconds (ROS 1 `time` and ROS 2
    /// `builtin_interfaces/Time` are both u32/i32 seconds + u32 nanoseconds).
    pub fn stamp_nanos(&mut self) -> Result<u64, WireError> {
        let sec = self.u32("header.stamp.sec")? as u64;
        let nsec = self.u32("header.stamp.nanosec")? as u64;
        Ok(sec * 1_000_000_000 + nsec)
    }

    /// Reads a `std_msgs/Header` (ROS 1 has a leading `seq`).
    pub fn header(&mut self) -> Result<(u64, &'a str), WireError> {
        if self.wire == Wire::Ros1 {
            self.u32("header.seq")?;
        }
        let stamp = self.stamp_nanos()?;
        let frame_id = self.string("header.frame_id")?;
        Ok((stamp, frame_id))
    }
}

/// Serializes one message; little-endian CDR or ROS 1.
pub struct WireWriter {
    buf: Vec<u8>,
    origin: usize,
    wire: Wire,
}

impl WireWriter {
    /// A little-endian CDR writer (encapsulation header `00 01 00 00`).
    pub fn cdr(capacity: usize) -> Self {
        let mut buf = Vec::with_capacity(capacity + 4);
        buf.extend_from_slice(&[0, 1, 0, 0]);
        WireWriter {
            buf,
            origin: 4,
            wire: Wire::Cdr { big_endian: false },
        }
    }

    pub fn ros1(capacity: usize) -> Self {
        WireWriter {
            buf: Vec::with_capacity(capacity),
            origin: 0,
            wire: Wire::Ros1,
        }
    }

    fn align(&mut self, n: usize) {
        if let Wire::Cdr { .. } = self.wire {
            let rel = self.buf.len() - self.origin;
            let pad = (n - rel % n) % n;
            self.buf.resize(self.buf.len() + pad, 0);
        }
    }

    pub fn u8(&mut self, v: u8) -> &mut Self {
        self.buf.push(v);
        self
    }

    pub fn u32(&mut self, v: u32) -> &mut Self {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
        self
    }

    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
        self
    }

    pub fn bytes(&mut self, v: &[u8]) -> &mut Self {
        self.u32(v.len() as u32);
        self.buf.extend_from_slice(v);
        self
    }

    pub fn string(&mut self, s: &str) -> &mut Self {
        match self.wire {
            Wire::Cdr { .. } => {
                self.u32(s.len() as u32 + 1);
                self.buf.extend_from_slice(s.as_bytes());
                self.buf.push(0);
            }
            Wire::Ros1 => {
                self.bytes(s.as_bytes());
            }
        }
        self
    }

    /// Writes a `std_msgs/Header` (ROS 1 with `seq` 0).
    pub fn header(&mut self, stamp_nanos: u64, frame_id: &str) -> &mut Self {
        if self.wire == Wire::Ros1 {
            self.u32(0);
        }
        self.u32((stamp_nanos / 1_000_000_000) as u32);
        self.u32((stamp_nanos % 1_000_000_000) as u32);
        self.string(frame_id)
    }

    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdr_aligns_after_the_encapsulation_header() {
        let mut w = WireWriter::cdr(16);
        w.u8(7).u32(0xdead_beef).string("ab").bytes(&[1, 2, 3]);
        let buf = w.finish();
        // header(4) u8(1) pad(3) u32(4) len(4) "ab\0"(3) pad(1) len(4) data(3)
        assert_eq!(buf.len(), 4 + 1 + 3 + 4 + 4 + 3 + 1 + 4 + 3);
        let mut r = WireReader::cdr(&buf).unwrap();
        assert_eq!(r.u8("a").unwrap(), 7);
        assert_eq!(r.u32("b").unwrap(), 0xdead_beef);
        assert_eq!(r.string("c").unwrap(), "ab");
        assert_eq!(r.bytes("d").unwrap(), &[1, 2, 3]);
        let err = r.u32("missing").unwrap_err();
        assert!(err.to_string().contains("missing"), "{err}");
    }

    #[test]
    fn big_endian_cdr_and_ros1_headers_read_back() {
        let buf = [0u8, 0, 0, 0, 0, 0, 0, 5];
        assert_eq!(WireReader::cdr(&buf).unwrap().u32("x").unwrap(), 5);
        assert!(WireReader::cdr(&[0x12, 0x34, 0, 0]).is_err());

        let mut w = WireWriter::ros1(8);
        w.header(3_000_000_007, "velodyne");
        let buf = w.finish();
        let mut r = WireReader::ros1(&buf);
        assert_eq!(r.header().unwrap(), (3_000_000_007, "velodyne"));
    }
}
