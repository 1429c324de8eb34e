//! Protobuf wire format, the little of it ONNX files need (runtime): iterate the fields of one
//! message without a schema, and write length-delimited and varint fields. Used by
//! [`crate::runtime::onnx_info`] (facts for `models check`) and [`crate::runtime::hoist`] (graph splitting).
//!
//! Wire types are protocolbuffers.dev/docs/encoding: 0 varint, 1 fixed64, 2 length-delimited,
//! 5 fixed32; groups (3, 4) are refused. Malformed input ends iteration with `None`, never a
//! panic, and every length is checked against the bytes that are there.

/// One field's value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Value<'a> {
    Varint(u64),
    Bytes(&'a [u8]),
    Fixed,
}

/// One field: its number, its value and its whole encoding (key included), to copy it as is.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Field<'a> {
    pub number: u64,
    pub value: Value<'a>,
    pub raw: &'a [u8],
}

/// Iterator over the fields of one message; a `None` item means malformed, and ends it.
pub(crate) struct Fields<'a> {
    rest: &'a [u8],
    failed: bool,
}

impl<'a> Fields<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        Self {
            rest: bytes,
            failed: false,
        }
    }

    fn next_field(&mut self) -> Option<Field<'a>> {
        let start = self.rest;
        let (key, used) = varint(self.rest)?;
        self.rest = &self.rest[used..];
        let value = match key & 7 {
            0 => {
                let (v, used) = varint(self.rest)?;
                self.rest = &self.rest[used..];
                Value::Varint(v)
            }
            1 | 5 => {
                let width = if key & 7 == 1 { 8 } else { 4 };
                self.rest = self.rest.get(width..)?;
                Value::Fixed
            }
            2 => {
                let (len, used) = varint(self.rest)?;
                let len = usize::try_from(len).ok()?;
                let bytes = self.rest.get(used..used.checked_add(len)?)?;
                self.rest = &self.rest[used + len..];
                Value::Bytes(bytes)
            }
            _ => return None,
        };
        let raw = &start[..start.len() - self.rest.len()];
        Some(Field {
            number: key >> 3,
            value,
            raw,
        })
    }
}

impl<'a> Field<'a> {
    /// (number, value), to match on both.
    pub fn pair(self) -> (u64, Value<'a>) {
        (self.number, self.value)
    }
}

impl<'a> Iterator for Fields<'a> {
    type Item = Option<Field<'a>>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed || self.rest.is_empty() {
            return None;
        }
        let field = self.next_field();
        self.failed = field.is_none();
        Some(field)
    }
}

/// A base-128 varint: value and bytes used.
pub(crate) fn varint(bytes: &[u8]) -> Option<(u64, usize)> {
    let mut value = 0u64;
    for (i, &b) in bytes.iter().enumerate().take(10) {
        value |= u64::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            return Some((value, i + 1));
        }
    }
    None
}

/// Append `value` as a base-128 varint.
pub(crate) fn put_varint(out: &mut Vec<u8>, mut value: u64) {
    while value >= 0x80 {
        out.push((value & 0x7f) as u8 | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

/// Append field `number` as a varint field.
pub(crate) fn put_varint_field(out: &mut Vec<u8>, number: u64, value: u64) {
    put_varint(out, number << 3);
    put_varint(out, value);
}

/// Append field `number` as a length-delimited field (string, bytes or sub-message).
pub(crate) fn put_bytes_field(out: &mut Vec<u8>, number: u64, payload: &[u8]) {
    put_varint(out, number << 3 | 2);
    put_varint(out, payload.len() as u64);
    out.extend_from_slice(payload);
}

/// A length-delimited field on its own (tests build messages with it).
#[cfg(test)]
pub(crate) fn bytes_field(number: u64, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    put_bytes_field(&mut out, number, payload);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn written_fields_read_back_with_their_raw_encoding() {
        let mut msg = Vec::new();
        put_varint_field(&mut msg, 1, 300);
        put_bytes_field(&mut msg, 7, &[0xaa; 200]);
        let fields: Vec<Field<'_>> = Fields::new(&msg).map(Option::unwrap).collect();
        assert_eq!(fields.len(), 2);
        assert_eq!((fields[0].number, fields[0].value), (1, Value::Varint(300)));
        assert_eq!(fields[0].raw, &[0x08, 0xac, 0x02]);
        assert_eq!(fields[1].number, 7);
        assert_eq!(fields[1].value, Value::Bytes(&[0xaa; 200]));
        assert_eq!(fields[1].raw.len(), 1 + 2 + 200);
        let rejoined: Vec<u8> = fields.iter().flat_map(|f| f.raw.iter().copied()).collect();
        assert_eq!(rejoined, msg);
    }

    #[test]
    fn malformed_messages_end_with_none() {
        let last = |bytes: &[u8]| Fields::new(bytes).last().flatten().map(|f| f.number);
        assert_eq!(last(&[0x3a, 200, 1, 2]), None); // length past the end
        assert_eq!(last(&[0x0b]), None); // wire type 3 (groups)
        assert_eq!(last(&[0x08, 0xff, 0xff]), None); // unterminated varint
        assert_eq!(last(&[0x09, 1, 2, 3]), None); // fixed64 cut short
        assert_eq!(last(&[0x08, 0x01]), Some(1));
    }
}
