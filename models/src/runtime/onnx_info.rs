//! A few facts read straight from ONNX protobuf bytes (runtime): IR version, opsets and how many
//! weight values the graph stores, for `choreod models check`. ONNX Runtime does not expose them.
//!
//! Field numbers are onnx/onnx:onnx/onnx.proto (ModelProto, GraphProto, NodeProto,
//! AttributeProto, TensorProto, OperatorSetIdProto). Malformed input gives `None`, never a panic.

use crate::runtime::proto::{Fields, Value, varint};

/// Summary of an ONNX model file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct OnnxInfo {
    /// `ModelProto.ir_version`.
    pub ir_version: i64,
    /// `(domain, version)` of every opset import; "" is the default ONNX domain.
    pub opsets: Vec<(String, i64)>,
    /// Elements of all stored tensors: initializers and tensor attributes (Constant nodes),
    /// including subgraphs. Counts every stored value, learned or not.
    pub stored_values: u64,
}

/// Nesting deeper than this is refused (protobuf's own default recursion limit is 100).
const MAX_DEPTH: usize = 64;

/// Parse `bytes` as a ModelProto.
pub fn inspect(bytes: &[u8]) -> Option<OnnxInfo> {
    let mut info = OnnxInfo::default();
    for field in Fields::new(bytes) {
        match field?.pair() {
            (1, Value::Varint(v)) => info.ir_version = v as i64,
            (7, Value::Bytes(graph)) => info.stored_values += graph_values(graph, 0)?,
            (8, Value::Bytes(opset)) => {
                let (mut domain, mut version) = (String::new(), 0i64);
                for f in Fields::new(opset) {
                    match f?.pair() {
                        (1, Value::Bytes(d)) => domain = String::from_utf8_lossy(d).into_owned(),
                        (2, Value::Varint(v)) => version = v as i64,
                        _ => {}
                    }
                }
                info.opsets.push((domain, version));
            }
            _ => {}
        }
    }
    Some(info)
}

/// GraphProto: initializer (5) tensors and the tensors inside node (1) attributes.
fn graph_values(graph: &[u8], depth: usize) -> Option<u64> {
    if depth > MAX_DEPTH {
        return None;
    }
    let mut total = 0u64;
    for field in Fields::new(graph) {
        match field?.pair() {
            (5, Value::Bytes(tensor)) => total = total.checked_add(tensor_elements(tensor)?)?,
            (1, Value::Bytes(node)) => {
                for f in Fields::new(node) {
                    if let (5, Value::Bytes(attribute)) = f?.pair() {
                        total = total.checked_add(attribute_values(attribute, depth)?)?;
                    }
                }
            }
            _ => {}
        }
    }
    Some(total)
}

/// AttributeProto: t (5), g (6), tensors (10), graphs (11).
fn attribute_values(attribute: &[u8], depth: usize) -> Option<u64> {
    let mut total = 0u64;
    for field in Fields::new(attribute) {
        let add = match field?.pair() {
            (5 | 10, Value::Bytes(tensor)) => tensor_elements(tensor)?,
            (6 | 11, Value::Bytes(graph)) => graph_values(graph, depth + 1)?,
            _ => 0,
        };
        total = total.checked_add(add)?;
    }
    Some(total)
}

/// TensorProto: product of `dims` (1), packed or not; a scalar has no dims and one element.
fn tensor_elements(tensor: &[u8]) -> Option<u64> {
    let mut product = 1u64;
    for field in Fields::new(tensor) {
        match field?.pair() {
            (1, Value::Varint(d)) => product = product.checked_mul(d)?,
            (1, Value::Bytes(packed)) => {
                let mut rest = packed;
                while !rest.is_empty() {
                    let (d, used) = varint(rest)?;
                    product = product.checked_mul(d)?;
                    rest = &rest[used..];
                }
            }
            _ => {}
        }
    }
    Some(product)
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::runtime::proto::bytes_field as field;

    /// A model whose graph nests `levels` subgraphs (node attribute g = 6).
    fn nested(levels: usize) -> Vec<u8> {
        let mut graph = field(5, &[0x08, 2]); // one initializer of 2 values
        for _ in 0..levels {
            graph = field(1, &field(5, &field(6, &graph)));
        }
        field(7, &graph)
    }

    #[test]
    fn counts_initializers_and_constants_and_reads_opsets() {
        // TensorProto dims [3, 4] unpacked, and [2, 5] packed.
        let t1 = [0x08, 3, 0x08, 4];
        let t2 = field(1, &[2, 5]);
        // A Constant node holding t2 in attribute `value` (t = 5), and t1 as an initializer.
        let attribute = field(5, &t2);
        let node = field(5, &attribute);
        let mut graph = field(1, &node);
        graph.extend(field(5, &t1));
        let mut model = vec![0x08, 10]; // ir_version 10
        model.extend(field(7, &graph));
        model.extend(field(8, &[0x10, 18])); // opset "" 18
        let info = inspect(&model).unwrap();
        assert_eq!(
            info,
            OnnxInfo {
                ir_version: 10,
                opsets: vec![(String::new(), 18)],
                stored_values: 22
            }
        );
    }

    #[test]
    fn malformed_bytes_are_none_not_a_panic() {
        assert_eq!(inspect(&[0x3a, 200, 1, 2]), None); // length past the end
        assert_eq!(inspect(&[0x0b]), None); // wire type 3 (groups)
        assert_eq!(inspect(&[0x08, 0xff, 0xff]), None); // unterminated varint
        assert_eq!(inspect(&nested(3)).map(|i| i.stored_values), Some(2));
        assert_eq!(inspect(&nested(MAX_DEPTH + 2)), None);
    }
}
