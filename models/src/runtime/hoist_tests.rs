//! Graph splitting on hand-built ModelProto bytes; the split packages are run against the whole
//! graphs in ONNX Runtime by models/tests/packages.rs.

use super::*;
use crate::runtime::proto::bytes_field as field;

fn node(op: &str, inputs: &[&str], outputs: &[&str]) -> Vec<u8> {
    let mut n = Vec::new();
    for i in inputs {
        n.extend(field(1, i.as_bytes()));
    }
    for o in outputs {
        n.extend(field(2, o.as_bytes()));
    }
    n.extend(field(4, op.as_bytes()));
    n
}

fn named(number: u64, name: &str) -> Vec<u8> {
    field(number, &field(1, name.as_bytes()))
}

/// A model over inputs x_t, t, music, cond with one initializer `w` and output `pred`.
fn model(nodes: &[Vec<u8>]) -> Vec<u8> {
    let mut graph = field(2, b"g");
    for n in nodes {
        graph.extend(field(1, n));
    }
    graph.extend(field(5, &field(8, b"w"))); // TensorProto with name 8 = "w"
    for i in ["x_t", "t", "music", "cond"] {
        graph.extend(named(11, i));
    }
    graph.extend(named(12, "pred"));
    let mut m = vec![0x08, 10]; // ir_version 10
    m.extend(field(7, &graph));
    m
}

/// (op types, node inputs, initializer names, input names, output names) of a ModelProto.
type Summary = (
    Vec<String>,
    Vec<String>,
    Vec<String>,
    Vec<String>,
    Vec<String>,
);

fn summary(model: &[u8]) -> Summary {
    let mut s: Summary = Default::default();
    let graph = Fields::new(model)
        .map(Option::unwrap)
        .find(|f| f.number == 7)
        .unwrap();
    let Value::Bytes(graph) = graph.value else {
        panic!("graph")
    };
    let text = |b: &[u8]| String::from_utf8(b.to_vec()).unwrap();
    for f in Fields::new(graph).map(Option::unwrap) {
        let Value::Bytes(b) = f.value else { continue };
        match f.number {
            1 => {
                for g in Fields::new(b).map(Option::unwrap) {
                    match g.pair() {
                        (4, Value::Bytes(op)) => s.0.push(text(op)),
                        (1, Value::Bytes(i)) => s.1.push(text(i)),
                        _ => {}
                    }
                }
            }
            5 => s.2.push(string_field(b, 8).unwrap().to_string()),
            11 => s.3.push(string_field(b, 1).unwrap().to_string()),
            12 => s.4.push(string_field(b, 1).unwrap().to_string()),
            _ => {}
        }
    }
    s
}

const STEP: [&str; 2] = ["x_t", "t"];

fn float_unknown() -> FrontierType {
    FrontierType {
        elem_type: 1,
        dims: vec![Dimension::Symbol("N".into()), Dimension::Fixed(4)],
    }
}

#[test]
fn music_only_work_moves_to_the_prologue() {
    let m = model(&[
        node("Constant", &[], &["two"]),
        node("MatMul", &["music", "w"], &["k"]),
        node("Mul", &["k", "two"], &["k2"]),
        node("Unsqueeze", &["cond", "two"], &["c"]),
        node("Add", &["x_t", "k2"], &["h"]),
        node("Mul", &["h", "two"], &["h2"]),
        node("Mul", &["h2", "c"], &["h3"]),
        node("Add", &["h3", "t"], &["pred"]),
        node("Neg", &["music"], &["dead"]), // read by nothing
    ]);
    let plan = HoistPlan::new(&m, &STEP).unwrap();
    assert_eq!(plan.frontier(), &["k2", "c"]);
    assert_eq!(plan.total_nodes(), 9);
    // MatMul, Mul and Unsqueeze leave the loop; Constant is in both graphs; Neg in neither.
    assert_eq!(plan.hoisted_nodes(), 3);

    let (ops, _, inits, inputs, outputs) = summary(&plan.prologue_model());
    assert_eq!(ops, ["Constant", "MatMul", "Mul", "Unsqueeze"]);
    assert_eq!(inits, ["w"]);
    assert_eq!(inputs, ["music", "cond"]);
    assert_eq!(outputs, ["k2", "c"]);

    let (ops, node_inputs, inits, inputs, outputs) =
        summary(&plan.step_model(&[float_unknown(), float_unknown()]));
    assert_eq!(ops, ["Constant", "Add", "Mul", "Mul", "Add"]);
    assert!(!node_inputs.iter().any(|i| i == "music" || i == "w"));
    assert!(inits.is_empty(), "w is only read by the prologue");
    assert_eq!(inputs, ["x_t", "t", "music", "cond", "k2", "c"]);
    assert_eq!(outputs, ["pred"]);
}

#[test]
fn step_inputs_declare_the_frontier_types() {
    let m = model(&[
        node("MatMul", &["music", "w"], &["k"]),
        node("Add", &["x_t", "k"], &["pred"]),
    ]);
    let plan = HoistPlan::new(&m, &STEP).unwrap();
    let ty = FrontierType {
        elem_type: 7,
        dims: vec![
            Dimension::Symbol("N".into()),
            Dimension::Unknown,
            Dimension::Fixed(157),
        ],
    };
    let step = plan.step_model(std::slice::from_ref(&ty));
    let mut expected = field(1, b"k");
    // type { tensor_type { elem_type 7, shape { dim {dim_param "N"} dim {} dim {dim_value 157} } } }
    let mut shape = field(1, &field(2, b"N"));
    shape.extend(field(1, &[]));
    shape.extend(field(1, &[0x08, 0x9d, 0x01]));
    let mut tensor = vec![0x08, 7];
    tensor.extend(field(2, &shape));
    expected.extend(field(2, &field(1, &tensor)));
    let needle = field(11, &expected);
    assert!(
        step.windows(needle.len()).any(|w| w == needle.as_slice()),
        "the step model declares k with its type"
    );
}

#[test]
fn graphs_that_cannot_be_split_say_why() {
    let reason = |nodes: &[Vec<u8>]| HoistPlan::new(&model(nodes), &STEP).unwrap_err();
    // Random operators stay in the loop, so here nothing is left to hoist.
    assert!(
        reason(&[
            node("RandomNormalLike", &["music"], &["r"]),
            node("Add", &["x_t", "r"], &["pred"]),
        ])
        .contains("no step-invariant work")
    );
    // Nor are other domains' operators hoisted.
    let mut custom = node("FusedThing", &["music"], &["r"]);
    custom.extend(field(7, b"com.example"));
    assert!(reason(&[custom, node("Add", &["x_t", "r"], &["pred"])]).contains("no step-invariant"));
    // An output computed from the music alone.
    assert!(reason(&[node("Neg", &["music"], &["pred"])]).contains("\"pred\""));
    // A subgraph (If with attribute g = 6).
    let mut with_graph = node("If", &["cond"], &["pred"]);
    with_graph.extend(field(5, &field(6, &field(2, b"branch"))));
    assert!(reason(&[with_graph]).contains("subgraph"));
    // Invalid graphs are left to ONNX Runtime to refuse whole.
    assert!(
        reason(&[
            node("Neg", &["music"], &["k"]),
            node("Neg", &["x_t"], &["k"]),
            node("Add", &["x_t", "k"], &["pred"]),
        ])
        .contains("defined twice")
    );
    assert!(reason(&[node("Add", &["x_t", "music"], &["w"])]).contains("defined twice"));
    // Constants alone are not worth a prologue.
    assert!(
        reason(&[
            node("Neg", &["w"], &["nw"]),
            node("Add", &["x_t", "nw"], &["pred"]),
        ])
        .contains("no step-invariant")
    );
}

#[test]
fn malformed_models_are_errors_not_panics() {
    let m = model(&[
        node("MatMul", &["music", "w"], &["k"]),
        node("Add", &["x_t", "k"], &["pred"]),
    ]);
    for cut in 0..m.len() {
        // Every prefix is malformed, empty or missing the graph: never a panic.
        let _ = HoistPlan::new(&m[..cut], &STEP);
    }
    assert!(HoistPlan::new(&[0x3a, 0xff], &STEP).is_err());
    assert!(HoistPlan::new(&[], &STEP).unwrap_err().contains("no graph"));
    let mut bad_name = model(&[]);
    bad_name.extend(field(7, &field(1, &field(1, &[0xff, 0xfe]))));
    assert!(HoistPlan::new(&bad_name, &STEP).is_err());
}
