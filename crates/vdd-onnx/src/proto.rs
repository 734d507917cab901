//! A minimal protobuf writer for the part of ONNX's schema (`onnx.proto`, IR version 8) that
//! the export uses: models, graphs, nodes, attributes, tensors and value infos. Field numbers
//! are the schema's; every message is written in one pass as nested length-delimited fields.

/// Protobuf wire types used here.
const VARINT: u32 = 0;
const FIXED32: u32 = 5;
const LEN: u32 = 2;

/// One protobuf message being written.
#[derive(Debug, Default, Clone)]
pub struct Msg(pub Vec<u8>);

impl Msg {
    /// An empty message.
    pub fn new() -> Self {
        Self(Vec::new())
    }

    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.0.push((v as u8 & 0x7f) | 0x80);
            v >>= 7;
        }
        self.0.push(v as u8);
    }

    fn key(&mut self, field: u32, wire: u32) {
        self.varint(u64::from(field << 3 | wire));
    }

    /// An integer field (`int32`, `int64`, enums; negative values as ten-byte varints).
    pub fn int(mut self, field: u32, v: i64) -> Self {
        self.key(field, VARINT);
        self.varint(v as u64);
        self
    }

    /// A `float` field.
    pub fn float(mut self, field: u32, v: f32) -> Self {
        self.key(field, FIXED32);
        self.0.extend_from_slice(&v.to_le_bytes());
        self
    }

    /// A `bytes` field.
    pub fn bytes(mut self, field: u32, v: &[u8]) -> Self {
        self.key(field, LEN);
        self.varint(v.len() as u64);
        self.0.extend_from_slice(v);
        self
    }

    /// A `string` field.
    pub fn string(self, field: u32, v: &str) -> Self {
        self.bytes(field, v.as_bytes())
    }

    /// A nested message field.
    pub fn msg(self, field: u32, m: &Msg) -> Self {
        self.bytes(field, &m.0)
    }
}

/// ONNX tensor element types (`TensorProto.DataType`).
pub const FLOAT: i64 = 1;
/// `int64`.
pub const INT64: i64 = 7;
/// `bool`.
pub const BOOL: i64 = 9;

/// A `TensorProto` with its values as little-endian `raw_data`.
pub fn tensor(name: &str, dims: &[usize], elem_type: i64, raw: &[u8]) -> Msg {
    let mut t = Msg::new();
    for &d in dims {
        t = t.int(1, d as i64);
    }
    t.int(2, elem_type).string(8, name).bytes(9, raw)
}

/// A `float` tensor.
pub fn f32_tensor(name: &str, dims: &[usize], values: &[f32]) -> Msg {
    let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    tensor(name, dims, FLOAT, &raw)
}

/// An `int64` tensor.
pub fn i64_tensor(name: &str, dims: &[usize], values: &[i64]) -> Msg {
    let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    tensor(name, dims, INT64, &raw)
}

/// A `bool` tensor.
pub fn bool_tensor(name: &str, dims: &[usize], values: &[bool]) -> Msg {
    let raw: Vec<u8> = values.iter().map(|&v| u8::from(v)).collect();
    tensor(name, dims, BOOL, &raw)
}

/// A dimension of a value's shape: fixed, or named (dynamic).
#[derive(Debug, Clone)]
pub enum Dim {
    /// A fixed size.
    Fixed(usize),
    /// A symbolic size (e.g. the batch `n`).
    Named(&'static str),
}

/// A `ValueInfoProto` of a float tensor.
pub fn value_info(name: &str, shape: &[Dim]) -> Msg {
    let mut s = Msg::new();
    for d in shape {
        let dim = match d {
            Dim::Fixed(v) => Msg::new().int(1, *v as i64),
            Dim::Named(p) => Msg::new().string(2, p),
        };
        s = s.msg(1, &dim);
    }
    let tensor_type = Msg::new().int(1, FLOAT).msg(2, &s);
    let ty = Msg::new().msg(1, &tensor_type);
    Msg::new().string(1, name).msg(2, &ty)
}

/// An attribute of a node.
#[derive(Debug, Clone)]
pub enum Attr {
    /// An integer (`AttributeType.INT`).
    Int(i64),
}

/// A `NodeProto`.
pub fn node(
    op: &str,
    name: &str,
    inputs: &[&str],
    outputs: &[&str],
    attrs: &[(&str, Attr)],
) -> Msg {
    let mut n = Msg::new();
    for i in inputs {
        n = n.string(1, i);
    }
    for o in outputs {
        n = n.string(2, o);
    }
    n = n.string(3, name).string(4, op);
    for (key, a) in attrs {
        let attr = match a {
            Attr::Int(v) => Msg::new().string(1, key).int(3, *v).int(20, 2),
        };
        n = n.msg(5, &attr);
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varints_and_fields_follow_the_wire_format() {
        // Field 1, varint 150: the protobuf documentation's example bytes.
        assert_eq!(Msg::new().int(1, 150).0, [0x08, 0x96, 0x01]);
        // A negative int64 is ten bytes.
        assert_eq!(Msg::new().int(1, -1).0.len(), 11);
        assert_eq!(Msg::new().string(2, "ab").0, [0x12, 2, b'a', b'b']);
        assert_eq!(Msg::new().float(2, 1.0).0, [0x15, 0, 0, 0x80, 0x3f]);
    }
}
