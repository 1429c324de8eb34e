//! A safe reader for the pickles AIST++ ships: a small subset of the pickle VM (protocols 2-5)
//! that builds plain values and numpy arrays and never runs code.
//!
//! GLOBAL / STACK_GLOBAL resolve only an allowlist (numpy's array reconstruction, `numpy.dtype`,
//! `numpy.ndarray`, numpy scalars, `_codecs.encode`); REDUCE and BUILD on those are interpreted
//! structurally. Every length is checked against the remaining input before allocating, and
//! stack, memo, nesting depth, copy work and the values decoded (by the input's size and the
//! element cap of [`crate::limits`]) are bounded. Opcode numbers from CPython
//! `Lib/pickletools.py`.

use std::collections::HashMap;
use std::path::Path;
use std::rc::Rc;

use choreo_dsp::quote;

use crate::error::{Error, Result};

/// Largest pickle read (AIST++ motions are < 2 MB; a long 60 fps take is < 50 MB).
pub const MAX_PICKLE_BYTES: u64 = 512 * 1024 * 1024;
const MAX_STACK: usize = 100_000;
const MAX_MEMO: usize = 1_000_000;
const MAX_DEPTH: u16 = 32;
/// Upper bound on elements copied when a shared list/dict is appended to (bounds hostile
/// quadratic copying).
const MAX_COPY_WORK: usize = 50_000_000;

/// A numpy array decoded from a pickle: C-order, values widened to f64 (exact for f32).
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    /// Shape.
    pub shape: Vec<usize>,
    /// Values in C order.
    pub data: Vec<f64>,
}

/// A decoded pickle value.
#[derive(Debug, Clone)]
pub enum Value {
    /// `None`.
    None,
    /// `True` / `False`.
    Bool(bool),
    /// An int that fits i64.
    Int(i64),
    /// A float.
    Float(f64),
    /// A str.
    Str(Rc<str>),
    /// bytes / py2 str.
    Bytes(Rc<Vec<u8>>),
    /// A tuple.
    Tuple(Rc<Vec<Value>>, u16),
    /// A list.
    List(Rc<Vec<Value>>, u16),
    /// A dict, in insertion order.
    Dict(Rc<Vec<(Value, Value)>>, u16),
    /// A numpy array.
    Array(Rc<NdArray>),
    /// An allowlisted callable or class.
    Global(Global),
    /// A numpy dtype (`descr` like "f4", byte order '<', '>', '|' or '=').
    Dtype { descr: Rc<str>, order: char },
    /// `_reconstruct(ndarray, ...)` waiting for its BUILD state.
    ArrayStub,
    /// A MARK on the stack.
    Mark,
}

/// The callables a pickle may name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Global {
    /// `numpy.core.multiarray._reconstruct` (or `numpy._core.multiarray._reconstruct`).
    Reconstruct,
    /// `numpy.ndarray`.
    Ndarray,
    /// `numpy.dtype`.
    Dtype,
    /// `numpy.core.multiarray.scalar`.
    Scalar,
    /// `_codecs.encode` (protocol-2 bytes).
    CodecsEncode,
    /// `numpy.core.numeric._frombuffer` (protocol-5 arrays: buffer, dtype, shape, order).
    FromBuffer,
}

impl Value {
    fn depth(&self) -> u16 {
        match self {
            Value::Tuple(_, d) | Value::List(_, d) | Value::Dict(_, d) => *d,
            _ => 0,
        }
    }

    fn type_name(&self) -> &'static str {
        match self {
            Value::None => "None",
            Value::Bool(_) => "bool",
            Value::Int(_) => "int",
            Value::Float(_) => "float",
            Value::Str(_) => "str",
            Value::Bytes(_) => "bytes",
            Value::Tuple(..) => "tuple",
            Value::List(..) => "list",
            Value::Dict(..) => "dict",
            Value::Array(_) => "ndarray",
            Value::Global(_) => "global",
            Value::Dtype { .. } => "dtype",
            Value::ArrayStub => "unfinished ndarray",
            Value::Mark => "mark",
        }
    }

    /// Look a string key up in a dict.
    pub fn get(&self, key: &str) -> Option<&Value> {
        match self {
            Value::Dict(items, _) => items
                .iter()
                .find(|(k, _)| matches!(k, Value::Str(s) if &**s == key))
                .map(|(_, v)| v),
            _ => None,
        }
    }
}

fn resolve_global(module: &str, name: &str) -> Option<Global> {
    match (module, name) {
        ("numpy.core.multiarray" | "numpy._core.multiarray", "_reconstruct") => {
            Some(Global::Reconstruct)
        }
        ("numpy", "ndarray") => Some(Global::Ndarray),
        ("numpy", "dtype") => Some(Global::Dtype),
        ("numpy.core.multiarray" | "numpy._core.multiarray", "scalar") => Some(Global::Scalar),
        ("_codecs", "encode") => Some(Global::CodecsEncode),
        ("numpy.core.numeric" | "numpy._core.numeric", "_frombuffer") => Some(Global::FromBuffer),
        _ => None,
    }
}

/// Read and decode a pickle file (see the module docs for what is accepted).
pub fn read_pickle(path: &Path) -> Result<Value> {
    let meta = std::fs::metadata(path).map_err(crate::error::io_err(path))?;
    if meta.len() > MAX_PICKLE_BYTES {
        return Err(Error::invalid(
            path,
            format!(
                "pickle is {} bytes, more than the {MAX_PICKLE_BYTES} accepted",
                meta.len()
            ),
        ));
    }
    let bytes = std::fs::read(path).map_err(crate::error::io_err(path))?;
    parse_pickle(&bytes).map_err(|(offset, reason)| {
        Error::invalid(
            path,
            format!("not a readable pickle (at byte {offset}): {reason}"),
        )
    })
}

type PResult<T> = std::result::Result<T, (usize, String)>;

struct Vm<'a> {
    data: &'a [u8],
    pos: usize,
    /// Offset of the opcode being run, for error messages.
    op_at: usize,
    stack: Vec<Value>,
    memo: HashMap<u32, Value>,
    copy_work: usize,
    /// Array values decoded so far.
    decoded: usize,
}

/// Decode pickle bytes; errors carry the byte offset of the failing opcode.
pub fn parse_pickle(data: &[u8]) -> PResult<Value> {
    let mut vm = Vm {
        data,
        pos: 0,
        op_at: 0,
        stack: Vec::new(),
        memo: HashMap::new(),
        copy_work: 0,
        decoded: 0,
    };
    vm.run()
}

impl<'a> Vm<'a> {
    fn err<T>(&self, reason: impl Into<String>) -> PResult<T> {
        Err((self.op_at, reason.into()))
    }

    fn take(&mut self, n: usize) -> PResult<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|e| *e <= self.data.len());
        match end {
            Some(end) => {
                let s = &self.data[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => self.err(format!(
                "truncated: needs {n} bytes, {} left",
                self.data.len().saturating_sub(self.pos)
            )),
        }
    }

    fn u8(&mut self) -> PResult<u8> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> PResult<u16> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32(&mut self) -> PResult<u32> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&mut self) -> PResult<u64> {
        let b = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(u64::from_le_bytes(a))
    }

    fn len64(&mut self) -> PResult<usize> {
        let n = self.u64()?;
        usize::try_from(n).or_else(|_| self.err(format!("length {n} too large")))
    }

    fn line(&mut self) -> PResult<&'a str> {
        let rest = &self.data[self.pos..];
        let Some(nl) = rest.iter().take(256).position(|b| *b == b'\n') else {
            return self.err("GLOBAL name without newline within 256 bytes");
        };
        self.pos += nl + 1;
        std::str::from_utf8(&rest[..nl]).or_else(|_| self.err("GLOBAL name is not UTF-8"))
    }

    fn push(&mut self, v: Value) -> PResult<()> {
        if self.stack.len() >= MAX_STACK {
            return self.err(format!("stack deeper than {MAX_STACK}"));
        }
        if v.depth() > MAX_DEPTH {
            return self.err(format!("values nested deeper than {MAX_DEPTH}"));
        }
        self.stack.push(v);
        Ok(())
    }

    fn pop(&mut self) -> PResult<Value> {
        match self.stack.pop() {
            Some(Value::Mark) => self.err("unexpected MARK"),
            Some(v) => Ok(v),
            None => self.err("stack underflow"),
        }
    }

    fn top_mut(&mut self) -> PResult<&mut Value> {
        let at = self.op_at;
        self.stack
            .last_mut()
            .ok_or((at, "stack underflow".to_owned()))
    }

    fn pop_mark(&mut self) -> PResult<Vec<Value>> {
        let Some(m) = self.stack.iter().rposition(|v| matches!(v, Value::Mark)) else {
            return self.err("no MARK on the stack");
        };
        let items = self.stack.split_off(m + 1);
        self.stack.pop();
        Ok(items)
    }

    fn tuple(&mut self, items: Vec<Value>) -> PResult<Value> {
        let depth = items.iter().map(Value::depth).max().unwrap_or(0) + 1;
        Ok(Value::Tuple(Rc::new(items), depth))
    }

    fn charge(&mut self, n: usize) -> PResult<()> {
        self.copy_work = self.copy_work.saturating_add(n);
        if self.copy_work > MAX_COPY_WORK {
            return self.err("too much copying of shared containers (hostile pickle?)");
        }
        Ok(())
    }

    fn run(&mut self) -> PResult<Value> {
        loop {
            self.op_at = self.pos;
            let op = self.u8()?;
            match op {
                0x80 => {
                    // PROTO
                    let p = self.u8()?;
                    if !(2..=5).contains(&p) {
                        return self.err(format!("pickle protocol {p} (supported: 2-5)"));
                    }
                }
                0x95 => {
                    // FRAME: a length hint; the data follows inline.
                    self.u64()?;
                }
                b'.' => {
                    // STOP
                    let v = self.pop()?;
                    return Ok(v);
                }
                b'(' => self.push(Value::Mark)?,
                b'N' => self.push(Value::None)?,
                0x88 => self.push(Value::Bool(true))?,
                0x89 => self.push(Value::Bool(false))?,
                b'K' => {
                    let v = self.u8()?;
                    self.push(Value::Int(i64::from(v)))?
                }
                b'M' => {
                    let v = self.u16()?;
                    self.push(Value::Int(i64::from(v)))?
                }
                b'J' => {
                    let v = self.u32()? as i32;
                    self.push(Value::Int(i64::from(v)))?
                }
                0x8a => {
                    // LONG1: little-endian two's complement of n bytes.
                    let n = usize::from(self.u8()?);
                    if n > 8 {
                        return self.err(format!("LONG1 of {n} bytes does not fit i64"));
                    }
                    let b = self.take(n)?;
                    let mut v: i64 = 0;
                    for (i, byte) in b.iter().enumerate() {
                        v |= i64::from(*byte) << (8 * i);
                    }
                    if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                        v -= 1i64 << (8 * n);
                    }
                    self.push(Value::Int(v))?
                }
                b'G' => {
                    let b = self.take(8)?;
                    let mut a = [0u8; 8];
                    a.copy_from_slice(b);
                    self.push(Value::Float(f64::from_be_bytes(a)))?
                }
                0x8c | b'X' | 0x8d => {
                    // SHORT_BINUNICODE, BINUNICODE, BINUNICODE8
                    let n = match op {
                        0x8c => usize::from(self.u8()?),
                        b'X' => self.u32()? as usize,
                        _ => self.len64()?,
                    };
                    let b = self.take(n)?;
                    let s = std::str::from_utf8(b).or_else(|_| self.err("str is not UTF-8"))?;
                    self.push(Value::Str(Rc::from(s)))?
                }
                b'C' | b'B' | 0x8e | b'U' | b'T' => {
                    // SHORT_BINBYTES, BINBYTES, BINBYTES8, SHORT_BINSTRING, BINSTRING
                    let n = match op {
                        b'C' | b'U' => usize::from(self.u8()?),
                        b'B' | b'T' => self.u32()? as usize,
                        _ => self.len64()?,
                    };
                    let b = self.take(n)?;
                    self.push(Value::Bytes(Rc::new(b.to_vec())))?
                }
                0x96 => {
                    // BYTEARRAY8
                    let n = self.len64()?;
                    let b = self.take(n)?;
                    self.push(Value::Bytes(Rc::new(b.to_vec())))?
                }
                b')' => {
                    let t = self.tuple(Vec::new())?;
                    self.push(t)?
                }
                0x85..=0x87 => {
                    let n = usize::from(op - 0x84);
                    if self.stack.len() < n {
                        return self.err("stack underflow");
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    if items.iter().any(|v| matches!(v, Value::Mark)) {
                        return self.err("unexpected MARK");
                    }
                    let t = self.tuple(items)?;
                    self.push(t)?
                }
                b't' => {
                    let items = self.pop_mark()?;
                    let t = self.tuple(items)?;
                    self.push(t)?
                }
                b']' => self.push(Value::List(Rc::new(Vec::new()), 1))?,
                b'l' => {
                    let items = self.pop_mark()?;
                    let depth = items.iter().map(Value::depth).max().unwrap_or(0) + 1;
                    self.push(Value::List(Rc::new(items), depth))?
                }
                b'}' => self.push(Value::Dict(Rc::new(Vec::new()), 1))?,
                b'a' | b'e' => {
                    // APPEND, APPENDS
                    let items = if op == b'a' {
                        vec![self.pop()?]
                    } else {
                        self.pop_mark()?
                    };
                    let add_depth = items.iter().map(Value::depth).max().unwrap_or(0) + 1;
                    let at = self.op_at;
                    let work = match self.top_mut()? {
                        Value::List(l, _) if Rc::strong_count(l) > 1 => l.len(),
                        _ => 0,
                    };
                    self.charge(work + items.len())?;
                    match self.top_mut()? {
                        Value::List(l, d) => {
                            Rc::make_mut(l).extend(items);
                            *d = (*d).max(add_depth);
                            if *d > MAX_DEPTH {
                                return Err((at, format!("values nested deeper than {MAX_DEPTH}")));
                            }
                        }
                        other => {
                            return Err((at, format!("APPEND to a {}", other.type_name())));
                        }
                    }
                }
                b's' | b'u' => {
                    // SETITEM, SETITEMS
                    let items = if op == b's' {
                        let v = self.pop()?;
                        let k = self.pop()?;
                        vec![k, v]
                    } else {
                        self.pop_mark()?
                    };
                    if items.len() % 2 != 0 {
                        return self.err("SETITEMS with an odd number of items");
                    }
                    let add_depth = items.iter().map(Value::depth).max().unwrap_or(0) + 1;
                    let at = self.op_at;
                    let work = match self.top_mut()? {
                        Value::Dict(l, _) if Rc::strong_count(l) > 1 => l.len(),
                        _ => 0,
                    };
                    self.charge(work + items.len())?;
                    match self.top_mut()? {
                        Value::Dict(dict, d) => {
                            let dict = Rc::make_mut(dict);
                            let mut it = items.into_iter();
                            while let (Some(k), Some(v)) = (it.next(), it.next()) {
                                dict.push((k, v));
                            }
                            *d = (*d).max(add_depth);
                            if *d > MAX_DEPTH {
                                return Err((at, format!("values nested deeper than {MAX_DEPTH}")));
                            }
                        }
                        other => {
                            return Err((at, format!("SETITEM on a {}", other.type_name())));
                        }
                    }
                }
                0x94 => {
                    // MEMOIZE
                    let idx = self.memo.len() as u32;
                    self.memo_put(idx)?
                }
                b'q' => {
                    let idx = u32::from(self.u8()?);
                    self.memo_put(idx)?
                }
                b'r' => {
                    let idx = self.u32()?;
                    self.memo_put(idx)?
                }
                b'h' | b'j' => {
                    let idx = if op == b'h' {
                        u32::from(self.u8()?)
                    } else {
                        self.u32()?
                    };
                    let Some(v) = self.memo.get(&idx).cloned() else {
                        return self.err(format!("memo entry {idx} not defined"));
                    };
                    self.push(v)?
                }
                b'c' => {
                    // GLOBAL "module\nname\n"
                    let module = self.line()?;
                    let name = self.line()?;
                    let g = self.global(module, name)?;
                    self.push(g)?
                }
                0x93 => {
                    // STACK_GLOBAL
                    let name = self.pop()?;
                    let module = self.pop()?;
                    let (Value::Str(m), Value::Str(n)) = (&module, &name) else {
                        return self.err("STACK_GLOBAL needs two strings");
                    };
                    let g = self.global(m, n)?;
                    self.push(g)?
                }
                b'R' => {
                    let args = self.pop()?;
                    let func = self.pop()?;
                    let v = self.reduce(func, args)?;
                    self.push(v)?
                }
                b'b' => {
                    let state = self.pop()?;
                    let obj = self.pop()?;
                    let v = self.build(obj, state)?;
                    self.push(v)?
                }
                b'0' => {
                    self.pop()?;
                }
                0x97 | 0x98 => {
                    return self.err("out-of-band buffers (protocol 5) are not supported");
                }
                other => {
                    return self.err(format!(
                        "opcode 0x{other:02x} is not allowed (only plain data and numpy arrays)"
                    ));
                }
            }
        }
    }

    fn memo_put(&mut self, idx: u32) -> PResult<()> {
        if self.memo.len() >= MAX_MEMO {
            return self.err(format!("more than {MAX_MEMO} memo entries"));
        }
        let Some(top) = self.stack.last() else {
            return self.err("memoize on an empty stack");
        };
        if matches!(top, Value::Mark) {
            return self.err("memoize a MARK");
        }
        let v = top.clone();
        self.memo.insert(idx, v);
        Ok(())
    }

    fn global(&self, module: &str, name: &str) -> PResult<Value> {
        match resolve_global(module, name) {
            Some(g) => Ok(Value::Global(g)),
            None => self.err(format!(
                "refusing global {} (not on the allowlist)",
                quote(&format!("{module}.{name}"))
            )),
        }
    }

    fn reduce(&mut self, func: Value, args: Value) -> PResult<Value> {
        let Value::Global(g) = func else {
            return self.err(format!(
                "REDUCE on a {} (only allowlisted globals)",
                func.type_name()
            ));
        };
        let Value::Tuple(args, _) = args else {
            return self.err("REDUCE arguments are not a tuple");
        };
        match g {
            Global::Reconstruct => match args.first() {
                Some(Value::Global(Global::Ndarray)) => Ok(Value::ArrayStub),
                _ => self.err("_reconstruct of something other than numpy.ndarray"),
            },
            Global::Dtype => match args.first() {
                Some(Value::Str(s)) => Ok(Value::Dtype {
                    descr: s.clone(),
                    order: '=',
                }),
                _ => self.err("numpy.dtype without a type string"),
            },
            Global::CodecsEncode => match (args.first(), args.get(1)) {
                (Some(Value::Str(s)), Some(Value::Str(enc))) if &**enc == "latin1" => {
                    let mut out = Vec::with_capacity(s.len());
                    for c in s.chars() {
                        let c = u32::from(c);
                        if c > 0xff {
                            return self.err("_codecs.encode: character outside latin1");
                        }
                        out.push(c as u8);
                    }
                    Ok(Value::Bytes(Rc::new(out)))
                }
                _ => self.err("_codecs.encode other than (str, 'latin1')"),
            },
            Global::Scalar => match (args.first(), args.get(1)) {
                (Some(Value::Dtype { descr, order }), Some(Value::Bytes(b))) => {
                    let vals = self.decode(descr, *order, b, 1)?;
                    Ok(Value::Float(vals[0]))
                }
                _ => self.err("numpy scalar without (dtype, bytes)"),
            },
            Global::FromBuffer => {
                let (
                    Some(Value::Bytes(raw)),
                    Some(Value::Dtype { descr, order }),
                    Some(Value::Tuple(dims, _)),
                ) = (args.first(), args.get(1), args.get(2))
                else {
                    return self.err("_frombuffer without (buffer, dtype, shape)");
                };
                if matches!(args.get(3), Some(Value::Str(o)) if &**o == "F") && dims.len() > 1 {
                    return self.err("Fortran-order arrays are not supported");
                }
                let shape = self.shape(dims)?;
                let count = shape.iter().product();
                let data = self.decode(descr, *order, raw, count)?;
                Ok(Value::Array(Rc::new(NdArray { shape, data })))
            }
            Global::Ndarray => self.err("calling numpy.ndarray directly is not supported"),
        }
    }

    fn build(&mut self, obj: Value, state: Value) -> PResult<Value> {
        let Value::Tuple(state, _) = state else {
            return self.err(format!(
                "BUILD state of a {} is not a tuple",
                obj.type_name()
            ));
        };
        match obj {
            Value::Dtype { descr, .. } => {
                // (version, byteorder, subdescr, names, fields, elsize, alignment, flags)
                let order = match state.get(1) {
                    Some(Value::Str(s)) if s.len() == 1 => s.chars().next().unwrap_or('='),
                    _ => return self.err("dtype state without a byte order"),
                };
                if !matches!(state.get(3), Some(Value::None) | None) {
                    return self.err("structured dtypes are not supported");
                }
                Ok(Value::Dtype { descr, order })
            }
            Value::ArrayStub => {
                // (version, shape, dtype, is_fortran, data)
                let (Some(shape), Some(dtype), Some(fortran), Some(raw)) =
                    (state.get(1), state.get(2), state.get(3), state.get(4))
                else {
                    return self.err("ndarray state has fewer than 5 fields");
                };
                let Value::Tuple(dims, _) = shape else {
                    return self.err("ndarray shape is not a tuple");
                };
                let shape_v = self.shape(dims)?;
                let count: usize = shape_v.iter().product();
                let Value::Dtype { descr, order } = dtype else {
                    return self.err("ndarray dtype is not a numpy.dtype");
                };
                if matches!(fortran, Value::Bool(true) | Value::Int(1)) && shape_v.len() > 1 {
                    return self.err("Fortran-order arrays are not supported");
                }
                let Value::Bytes(raw) = raw else {
                    return self.err("ndarray data is not bytes (object arrays are not supported)");
                };
                let data = self.decode(descr, *order, raw, count)?;
                Ok(Value::Array(Rc::new(NdArray {
                    shape: shape_v,
                    data,
                })))
            }
            other => self.err(format!("BUILD on a {}", other.type_name())),
        }
    }

    /// A shape tuple as sizes, refusing negative sizes and products that overflow.
    fn shape(&self, dims: &[Value]) -> PResult<Vec<usize>> {
        let mut shape = Vec::with_capacity(dims.len().min(32));
        let mut count: usize = 1;
        for d in dims {
            let Value::Int(d) = d else {
                return self.err("ndarray dimension is not an int");
            };
            let d = usize::try_from(*d).or_else(|_| self.err(format!("negative dimension {d}")))?;
            count = count
                .checked_mul(d)
                .ok_or((self.op_at, "ndarray shape overflows".to_owned()))?;
            shape.push(d);
        }
        Ok(shape)
    }

    /// Decode `count` numbers of numpy type `descr` from `raw`, checking the size first.
    fn decode(&mut self, descr: &str, order: char, raw: &[u8], count: usize) -> PResult<Vec<f64>> {
        let descr = descr.trim_start_matches(['<', '>', '|', '=']);
        let big = order == '>';
        let size = match descr {
            "f4" | "i4" | "u4" => 4,
            "f8" | "i8" | "u8" => 8,
            "f2" | "i2" | "u2" => 2,
            "i1" | "u1" | "b1" => 1,
            other => return self.err(format!("unsupported dtype {}", quote(other))),
        };
        let need = count
            .checked_mul(size)
            .ok_or((self.op_at, "array size overflows".to_owned()))?;
        if need != raw.len() {
            return self.err(format!(
                "array of {count} × {descr} needs {need} bytes, the pickle holds {}",
                raw.len()
            ));
        }
        // Every value decoded takes at least one byte of the pickle, unless a memoised buffer is
        // decoded again and again: bound the total by the input's size and the element cap.
        self.decoded = self.decoded.saturating_add(count);
        let budget = self.data.len().min(crate::limits::max_elements());
        if self.decoded > budget {
            return self.err(format!(
                "arrays of {} values in total, more than the {budget} this pickle can hold (buffers reused?)",
                self.decoded
            ));
        }
        let mut out = Vec::with_capacity(count);
        for c in raw.chunks_exact(size) {
            let mut b = [0u8; 8];
            b[..size].copy_from_slice(c);
            if big {
                b[..size].reverse();
            }
            let v = match descr {
                "f4" => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                "f8" => f64::from_le_bytes(b),
                "f2" => half_to_f64(u16::from_le_bytes([b[0], b[1]])),
                "i4" => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                "u4" => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                "i8" => i64::from_le_bytes(b) as f64,
                "u8" => u64::from_le_bytes(b) as f64,
                "i2" => f64::from(i16::from_le_bytes([b[0], b[1]])),
                "u2" => f64::from(u16::from_le_bytes([b[0], b[1]])),
                "i1" => f64::from(b[0] as i8),
                _ => f64::from(b[0]),
            };
            out.push(v);
        }
        Ok(out)
    }
}

fn half_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = i32::from((h >> 10) & 0x1f);
    let frac = f64::from(h & 0x3ff);
    sign * match exp {
        0 => frac * 2f64.powi(-24),
        31 if frac == 0.0 => f64::INFINITY,
        31 => f64::NAN,
        e => (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture() -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")
    }

    #[test]
    fn reads_the_aistpp_fixture() {
        let v = read_pickle(&fixture()).unwrap();
        let Some(Value::Array(p)) = v.get("smpl_poses") else {
            panic!("no poses")
        };
        assert_eq!(p.shape, vec![720, 72]);
        let Some(Value::Array(s)) = v.get("smpl_scaling") else {
            panic!("no scaling")
        };
        // value printed by numpy from the same file: 93.77886
        assert!((s.data[0] - 93.77886).abs() < 1e-4);
        assert!(matches!(v.get("smpl_loss"), Some(Value::Float(_))));
    }

    #[test]
    fn every_truncation_is_an_error_not_a_panic() {
        let bytes = std::fs::read(fixture()).unwrap();
        // Cut inside the header, inside the array bytes, and just before STOP.
        for cut in [1, 2, 11, 60, 150, 190, 5000, bytes.len() - 1] {
            assert!(parse_pickle(&bytes[..cut]).is_err(), "cut at {cut} parsed");
        }
    }

    #[test]
    fn refuses_arbitrary_globals() {
        // protocol 2: GLOBAL os.system, args ('echo',), REDUCE, STOP
        let p = b"\x80\x02cos\nsystem\nX\x04\x00\x00\x00echo\x85R.";
        let e = parse_pickle(p).unwrap_err();
        assert!(e.1.contains("os.system"), "{e:?}");
    }

    #[test]
    fn huge_declared_lengths_are_rejected_before_allocating() {
        // BINBYTES8 claiming 2^60 bytes.
        let mut p = b"\x80\x04\x8e".to_vec();
        p.extend_from_slice(&(1u64 << 60).to_le_bytes());
        assert!(parse_pickle(&p).unwrap_err().1.contains("truncated"));
        // LONG_BINPUT to index 4e9 must not size a vector.
        let p = b"\x80\x02Nr\x00\x00\x00\xf0.";
        assert!(parse_pickle(p).is_ok());
    }

    /// `{'smpl_poses': [_frombuffer(buf, u1, (n,), 'C')] * copies}` with `buf` (n bytes) stored
    /// once and fetched from the memo for every further array.
    fn reused_buffer_pickle(n: usize, copies: usize) -> Vec<u8> {
        let mut p = b"\x80\x04}\x8c\x0asmpl_poses](".to_vec();
        for i in 0..copies {
            p.extend_from_slice(b"cnumpy.core.numeric\n_frombuffer\n(");
            if i == 0 {
                p.push(b'B');
                p.extend_from_slice(&(n as u32).to_le_bytes());
                p.extend(std::iter::repeat_n(7u8, n));
                p.push(0x94); // MEMOIZE as entry 0
            } else {
                p.extend_from_slice(b"h\x00"); // BINGET 0
            }
            p.extend_from_slice(b"cnumpy\ndtype\n\x8c\x02u1\x85R");
            p.push(b'J');
            p.extend_from_slice(&(n as i32).to_le_bytes());
            p.extend_from_slice(b"\x85\x8c\x01CtR");
        }
        p.extend_from_slice(b"es.");
        p
    }

    #[test]
    fn a_reused_buffer_cannot_multiply_the_output() {
        // Decoded once, the buffer is fine: each value has its byte in the pickle.
        let v = parse_pickle(&reused_buffer_pickle(1000, 1)).unwrap();
        let Some(Value::List(l, _)) = v.get("smpl_poses") else {
            panic!("no list")
        };
        assert!(matches!(&l[0], Value::Array(a) if a.data.len() == 1000 && a.data[999] == 7.0));
        // Decoded three times it claims three values per byte of input.
        let e = parse_pickle(&reused_buffer_pickle(1000, 3)).unwrap_err();
        assert!(e.1.contains("buffers reused"), "{e:?}");
    }

    #[test]
    fn deep_nesting_is_bounded() {
        let mut p = b"\x80\x02N".to_vec();
        p.extend(std::iter::repeat_n(0x85u8, 10_000));
        p.push(b'.');
        assert!(parse_pickle(&p).unwrap_err().1.contains("nested"));
    }

    #[test]
    fn array_shape_must_match_its_bytes() {
        // Take the fixture and claim 721 rows instead of 720 (BININT2 at offset 124).
        let mut bytes = std::fs::read(fixture()).unwrap();
        assert_eq!(&bytes[124..127], &[b'M', 0xd0, 0x02]);
        bytes[125] = 0xd1;
        let e = parse_pickle(&bytes).unwrap_err();
        assert!(e.1.contains("needs"), "{e:?}");
    }
}
