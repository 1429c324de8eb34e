//! Step-invariant work hoisted out of the denoising loop (runtime).
//!
//! A denoiser runs once per step on the same conditions; only its step inputs (`x_t` and `t`,
//! named by the package's task) change. Whatever the graph computes from the other inputs alone
//! — MoFusion's projected log-mel and every cross-attention's keys and values, the exemplar's
//! beat-retimed candidates, MCM-LDM's trajectory encoding — comes out the same at every step.
//! [`HoistPlan`] splits a graph in two (loop-invariant code motion):
//!
//! - the **prologue** computes those tensors (the *frontier*: step-invariant tensors that
//!   step-dependent nodes read) from the invariant inputs, once per batch;
//! - the **step** graph is the rest, with the frontier as extra inputs.
//!
//! Both hold the original nodes byte for byte, so the step graph computes what the whole graph
//! computes. Not hoisted, and so left in the step graph: nodes of other domains than ONNX's own,
//! random operators and `Dropout`. Graphs with subgraphs (`If`, `Loop`, `Scan`), sparse
//! initializers or an output that depends on the invariant inputs alone are not split at all.
//!
//! Field numbers are onnx/onnx:onnx/onnx.proto (ModelProto graph 7; GraphProto node 1, name 2,
//! initializer 5, input 11, output 12, sparse_initializer 15; NodeProto input 1, output 2,
//! op_type 4, attribute 5, domain 7; AttributeProto g 6, graphs 11; TensorProto name 8;
//! ValueInfoProto name 1, type 2; TypeProto tensor_type 1; TypeProto.Tensor elem_type 1, shape 2;
//! TensorShapeProto dim 1; Dimension dim_value 1, dim_param 2).

use std::collections::{HashMap, HashSet};

use crate::runtime::proto::{Field, Fields, Value, put_bytes_field, put_varint_field};

/// Operators whose output may differ between two runs on the same inputs: never hoisted.
/// (`Dropout` is the identity at inference, but training-mode exports make it random.)
const RANDOM_OPS: [&str; 7] = [
    "RandomNormal",
    "RandomNormalLike",
    "RandomUniform",
    "RandomUniformLike",
    "Multinomial",
    "Bernoulli",
    "Dropout",
];

/// How a tensor depends on the inputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Class {
    /// Initializers and what is computed from them alone.
    Constant,
    /// Computed from the invariant inputs (and constants): the same at every step.
    Invariant,
    /// Depends on a step input, or not safely hoistable.
    Step,
}

#[derive(Debug)]
struct Node<'a> {
    raw: &'a [u8],
    inputs: Vec<&'a str>,
    outputs: Vec<&'a str>,
    /// An ONNX-domain, deterministic operator: may move to the prologue.
    hoistable: bool,
}

/// A model split into prologue and step graphs; see the module docs.
#[derive(Debug)]
pub(crate) struct HoistPlan<'a> {
    /// ModelProto fields other than the graph, copied into both models.
    model_fields: Vec<&'a [u8]>,
    /// The graph's name field, if any.
    graph_name: Option<&'a [u8]>,
    nodes: Vec<Node<'a>>,
    /// (name, raw field) of every initializer.
    initializers: Vec<(&'a str, &'a [u8])>,
    /// (name, raw field) of every graph input.
    inputs: Vec<(&'a str, &'a [u8])>,
    /// Raw fields of the graph outputs.
    outputs: Vec<&'a [u8]>,
    frontier: Vec<&'a str>,
    prologue_nodes: Vec<usize>,
    step_nodes: Vec<usize>,
}

/// Element type and shape of one frontier tensor, as ONNX Runtime inferred them for the
/// prologue's outputs; declared on the step graph's inputs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct FrontierType {
    /// ONNX `TensorProto.DataType` (1 = float, 7 = int64, ...).
    pub elem_type: i32,
    pub dims: Vec<Dimension>,
}

/// One axis of a [`FrontierType`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Dimension {
    Fixed(i64),
    Symbol(String),
    Unknown,
}

impl<'a> HoistPlan<'a> {
    /// Plan the split of the ModelProto `model`, whose inputs named in `step_inputs` change from
    /// step to step (all others are invariant). `Err` says why the graph is not split; the
    /// caller then runs the whole graph at every step.
    pub fn new(model: &'a [u8], step_inputs: &[&str]) -> Result<Self, String> {
        let malformed = || "the file is not a well-formed ONNX model".to_string();
        let mut model_fields = Vec::new();
        let mut graph = None;
        for field in Fields::new(model) {
            let field = field.ok_or_else(malformed)?;
            match field.pair() {
                (7, Value::Bytes(g)) => graph = Some(g),
                _ => model_fields.push(field.raw),
            }
        }
        let graph = graph.ok_or_else(|| "the model has no graph".to_string())?;
        let mut plan = Self {
            model_fields,
            graph_name: None,
            nodes: Vec::new(),
            initializers: Vec::new(),
            inputs: Vec::new(),
            outputs: Vec::new(),
            frontier: Vec::new(),
            prologue_nodes: Vec::new(),
            step_nodes: Vec::new(),
        };
        let mut output_names = Vec::new();
        for field in Fields::new(graph) {
            let field = field.ok_or_else(malformed)?;
            match field.pair() {
                (1, Value::Bytes(node)) => plan.nodes.push(parse_node(node, field.raw)?),
                (2, Value::Bytes(_)) => plan.graph_name = Some(field.raw),
                (5, Value::Bytes(tensor)) => {
                    plan.initializers
                        .push((string_field(tensor, 8)?, field.raw));
                }
                (11, Value::Bytes(info)) => plan.inputs.push((string_field(info, 1)?, field.raw)),
                (12, Value::Bytes(info)) => {
                    output_names.push(string_field(info, 1)?);
                    plan.outputs.push(field.raw);
                }
                (15, _) => return Err("the graph has sparse initializers".into()),
                // doc_string, value_info, quantization annotations, metadata: not needed to run.
                _ => {}
            }
        }
        plan.classify(step_inputs, &output_names)?;
        Ok(plan)
    }

    /// Sort nodes into prologue and step and find the frontier.
    fn classify(&mut self, step_inputs: &[&str], output_names: &[&'a str]) -> Result<(), String> {
        let mut class: HashMap<&str, Class> = HashMap::new();
        for (name, _) in &self.initializers {
            class.insert(name, Class::Constant);
        }
        for (name, _) in &self.inputs {
            if class.contains_key(name) {
                // Pre-IR-4 style: an input with a default value; it may be fed or not.
                return Err(format!("input {name:?} is also an initializer"));
            }
            let c = if step_inputs.contains(name) {
                Class::Step
            } else {
                Class::Invariant
            };
            class.insert(name, c);
        }
        let mut node_class = Vec::with_capacity(self.nodes.len());
        for node in &self.nodes {
            // Nodes are topologically sorted (an ONNX rule); an input not seen yet is Step.
            let c = if !node.hoistable {
                Class::Step
            } else {
                node.inputs
                    .iter()
                    .filter(|i| !i.is_empty())
                    .map(|i| class.get(i).copied().unwrap_or(Class::Step))
                    .fold(Class::Constant, |a, b| match (a, b) {
                        (Class::Step, _) | (_, Class::Step) => Class::Step,
                        (Class::Invariant, _) | (_, Class::Invariant) => Class::Invariant,
                        _ => Class::Constant,
                    })
            };
            for o in node.outputs.iter().filter(|o| !o.is_empty()) {
                // Invalid ONNX (ORT refuses it whole); split, each half might load.
                if class.insert(o, c).is_some() {
                    return Err(format!("tensor {o:?} is defined twice"));
                }
            }
            node_class.push(c);
        }
        if let Some(out) = output_names
            .iter()
            .find(|o| class.get(*o) == Some(&Class::Invariant))
        {
            return Err(format!(
                "output {out:?} depends on the invariant inputs alone"
            ));
        }
        // Invariant tensors computed by nodes (invariant graph inputs are simply fed).
        let computed: HashSet<&str> = self
            .nodes
            .iter()
            .zip(&node_class)
            .filter(|(_, c)| **c == Class::Invariant)
            .flat_map(|(n, _)| n.outputs.iter().copied())
            .collect();
        let mut seen = HashSet::new();
        for (node, c) in self.nodes.iter().zip(&node_class) {
            if *c == Class::Invariant {
                continue;
            }
            for i in &node.inputs {
                if computed.contains(i) && seen.insert(*i) {
                    self.frontier.push(i);
                }
            }
        }
        if self.frontier.is_empty() {
            return Err("no step-invariant work to hoist".into());
        }
        let producer: HashMap<&str, usize> = self
            .nodes
            .iter()
            .enumerate()
            .flat_map(|(k, n)| n.outputs.iter().map(move |o| (*o, k)))
            .collect();
        let frontier: HashSet<&str> = self.frontier.iter().copied().collect();
        self.prologue_nodes = closure(&self.nodes, &producer, &self.frontier, &HashSet::new());
        self.step_nodes = closure(&self.nodes, &producer, output_names, &frontier);
        Ok(())
    }

    /// Names of the frontier tensors: the prologue's outputs and the step graph's extra inputs.
    pub fn frontier(&self) -> &[&'a str] {
        &self.frontier
    }

    /// Nodes moved out of the loop: those in the prologue and not in the step graph.
    pub fn hoisted_nodes(&self) -> usize {
        self.prologue_nodes
            .iter()
            .filter(|k| self.step_nodes.binary_search(k).is_err())
            .count()
    }

    /// Nodes of the whole graph.
    pub fn total_nodes(&self) -> usize {
        self.nodes.len()
    }

    /// The prologue as a ModelProto: the inputs its nodes read, the frontier as outputs (left
    /// untyped: ONNX Runtime infers them).
    pub fn prologue_model(&self) -> Vec<u8> {
        let used = self.used_names(&self.prologue_nodes);
        let mut graph = Vec::new();
        self.put_nodes_and_weights(&mut graph, &self.prologue_nodes, &used);
        for (name, raw) in &self.inputs {
            if used.contains(name) {
                graph.extend_from_slice(raw);
            }
        }
        for name in &self.frontier {
            let mut info = Vec::new();
            put_bytes_field(&mut info, 1, name.as_bytes());
            put_bytes_field(&mut graph, 12, &info);
        }
        self.model_with(&graph)
    }

    /// The step graph as a ModelProto: every original input (so its interface is the whole
    /// graph's), then the frontier typed as `types` (in [`Self::frontier`] order).
    pub fn step_model(&self, types: &[FrontierType]) -> Vec<u8> {
        debug_assert_eq!(types.len(), self.frontier.len());
        let used = self.used_names(&self.step_nodes);
        let mut graph = Vec::new();
        self.put_nodes_and_weights(&mut graph, &self.step_nodes, &used);
        for (_, raw) in &self.inputs {
            graph.extend_from_slice(raw);
        }
        for (name, ty) in self.frontier.iter().zip(types) {
            put_bytes_field(&mut graph, 11, &value_info(name, ty));
        }
        for raw in &self.outputs {
            graph.extend_from_slice(raw);
        }
        self.model_with(&graph)
    }

    fn used_names(&self, nodes: &[usize]) -> HashSet<&'a str> {
        nodes
            .iter()
            .flat_map(|&k| self.nodes[k].inputs.iter().copied())
            .collect()
    }

    fn put_nodes_and_weights(&self, graph: &mut Vec<u8>, nodes: &[usize], used: &HashSet<&str>) {
        if let Some(name) = self.graph_name {
            graph.extend_from_slice(name);
        }
        for &k in nodes {
            graph.extend_from_slice(self.nodes[k].raw);
        }
        for (name, raw) in &self.initializers {
            if used.contains(name) {
                graph.extend_from_slice(raw);
            }
        }
    }

    fn model_with(&self, graph: &[u8]) -> Vec<u8> {
        let mut model: Vec<u8> = self.model_fields.concat();
        put_bytes_field(&mut model, 7, graph);
        model
    }
}

/// Indices (sorted) of the nodes needed to compute `targets`, not looking past `given`.
fn closure(
    nodes: &[Node<'_>],
    producer: &HashMap<&str, usize>,
    targets: &[&str],
    given: &HashSet<&str>,
) -> Vec<usize> {
    let mut needed = vec![false; nodes.len()];
    let mut stack: Vec<&str> = targets.to_vec();
    let mut visited = HashSet::new();
    while let Some(name) = stack.pop() {
        if given.contains(name) || !visited.insert(name) {
            continue;
        }
        if let Some(&k) = producer.get(name)
            && !needed[k]
        {
            needed[k] = true;
            stack.extend(nodes[k].inputs.iter().filter(|i| !i.is_empty()));
        }
    }
    (0..nodes.len()).filter(|&k| needed[k]).collect()
}

/// A NodeProto's inputs, outputs and whether it may be hoisted (`raw` is its graph field).
fn parse_node<'a>(node: &'a [u8], raw: &'a [u8]) -> Result<Node<'a>, String> {
    let malformed = || "a node is not well-formed".to_string();
    let (mut inputs, mut outputs) = (Vec::new(), Vec::new());
    let (mut op, mut domain) = ("", "");
    for field in Fields::new(node) {
        match field.ok_or_else(malformed)?.pair() {
            (1, Value::Bytes(s)) => inputs.push(utf8(s)?),
            (2, Value::Bytes(s)) => outputs.push(utf8(s)?),
            (4, Value::Bytes(s)) => op = utf8(s)?,
            (7, Value::Bytes(s)) => domain = utf8(s)?,
            (5, Value::Bytes(attribute)) => {
                for f in Fields::new(attribute) {
                    if let (6 | 11, _) = f.ok_or_else(malformed)?.pair() {
                        return Err(format!("node {op:?} has a subgraph"));
                    }
                }
            }
            _ => {}
        }
    }
    Ok(Node {
        raw,
        inputs,
        outputs,
        hoistable: matches!(domain, "" | "ai.onnx") && !RANDOM_OPS.contains(&op),
    })
}

fn utf8(bytes: &[u8]) -> Result<&str, String> {
    std::str::from_utf8(bytes).map_err(|_| "a name is not UTF-8".to_string())
}

/// The string field `number` of a message (a name), "" when absent.
fn string_field(message: &[u8], number: u64) -> Result<&str, String> {
    let mut name = "";
    for field in Fields::new(message) {
        let field: Field<'_> = field.ok_or_else(|| "a value is not well-formed".to_string())?;
        if let (n, Value::Bytes(s)) = field.pair()
            && n == number
        {
            name = utf8(s)?;
        }
    }
    Ok(name)
}

/// A ValueInfoProto for a tensor input.
fn value_info(name: &str, ty: &FrontierType) -> Vec<u8> {
    let mut shape = Vec::new();
    for d in &ty.dims {
        let mut dim = Vec::new();
        match d {
            Dimension::Fixed(n) => put_varint_field(&mut dim, 1, *n as u64),
            Dimension::Symbol(s) => put_bytes_field(&mut dim, 2, s.as_bytes()),
            Dimension::Unknown => {}
        }
        put_bytes_field(&mut shape, 1, &dim);
    }
    let mut tensor = Vec::new();
    put_varint_field(&mut tensor, 1, ty.elem_type as u64);
    put_bytes_field(&mut tensor, 2, &shape);
    let mut type_proto = Vec::new();
    put_bytes_field(&mut type_proto, 1, &tensor);
    let mut info = Vec::new();
    put_bytes_field(&mut info, 1, name.as_bytes());
    put_bytes_field(&mut info, 2, &type_proto);
    info
}

#[cfg(test)]
#[path = "hoist_tests.rs"]
mod tests;
