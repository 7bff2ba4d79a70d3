//! A safe reader for Python pickles (protocols 0 to 5) of dicts, lists and numpy arrays.
//!
//! This is a pickle virtual machine that executes nothing: `GLOBAL` and `STACK_GLOBAL` only
//! resolve names on a fixed allow list (numpy's array, dtype and scalar reconstructors in both
//! the numpy 1 `numpy.core` and numpy 2 `numpy._core` spellings, `collections.OrderedDict`,
//! `_codecs.encode`, `bytes`, `bytearray`, `set`), and `REDUCE`/`BUILD` on those names are interpreted
//! by this module. Every other global, persistent ids, extension codes and out-of-band
//! buffers are errors.
//!
//! Memory is bounded by the input: every length read from the file is checked against the
//! bytes that remain, the machine's objects live in an arena (so memo references share
//! objects the way Python's do, and mutation after memoisation is seen by every reference),
//! and turning the arena into a [`Value`] tree has a budget proportional to the input size,
//! so shared references cannot expand exponentially and cycles are rejected.

use std::collections::HashMap;

use super::dtype::{DType, Kind};
use super::value::{ArrayData, NpArray, Value};
use super::{Budget, OverBudget};

/// Why a pickle was rejected. Offsets are byte positions in the pickle stream.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PickleError {
    #[error("truncated pickle: {what} needs more bytes than remain (at byte {offset})")]
    Truncated { what: &'static str, offset: usize },
    #[error("unknown pickle opcode 0x{opcode:02x} at byte {offset}")]
    UnknownOpcode { opcode: u8, offset: usize },
    #[error("pickle opcode {name} at byte {offset} is not supported: {why}")]
    Unsupported {
        name: &'static str,
        offset: usize,
        why: &'static str,
    },
    #[error(
        "pickle refers to {module}.{name} (at byte {offset}), which this reader does not \
         allow: it only rebuilds numpy arrays, dtypes, scalars, dicts, OrderedDicts and lists{hint}"
    )]
    ForbiddenGlobal {
        module: String,
        name: String,
        offset: usize,
        hint: &'static str,
    },
    #[error("malformed pickle at byte {offset}: {message}")]
    Malformed { offset: usize, message: String },
    #[error("pickle decodes to more than {limit} bytes of values (shared references expand)")]
    TooLarge { limit: usize },
    #[error("pickle nests deeper than {limit} levels or contains a reference cycle")]
    TooDeep { limit: usize },
    #[error("pickle stream ended without a STOP opcode")]
    NoStop,
    #[error(transparent)]
    Limit(#[from] super::BadLimit),
}

/// Maximum nesting of containers in the decoded value.
pub const MAX_DEPTH: usize = 128;

/// Decodes a complete pickle. Bytes after the `STOP` opcode are ignored, as Python does.
/// Decoded values may take [`super::decode_budget`] of the input's size, within the
/// per-file limit of [`super::Limits::from_env`].
pub fn load(bytes: &[u8]) -> Result<Value, PickleError> {
    let limits = super::Limits::from_env()?;
    let (value, _) = load_prefix_within(bytes, &mut Budget::for_pickle(bytes.len(), &limits))?;
    Ok(value)
}

/// Decodes one pickle from the start of `bytes`, and how many bytes it used, with the
/// decoded values (the machine's arrays and the final tree) charged to `budget`, which an
/// enclosing file (an `.npy` object array) shares.
pub fn load_prefix_within(
    bytes: &[u8],
    budget: &mut Budget,
) -> Result<(Value, usize), PickleError> {
    let mut machine = Machine::new(bytes, budget.clone());
    let root = machine.run()?;
    let used = machine.pos;
    let mut builder = Builder {
        arena: &machine.arena,
        budget: machine.budget.clone(),
        in_progress: vec![false; machine.arena.len()],
    };
    let value = builder.build(root, 0)?;
    *budget = builder.budget;
    Ok((value, used))
}

type Id = usize;

/// The callables on the allow list.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Global {
    Reconstruct,
    NdarrayType,
    DtypeType,
    Scalar,
    FromBuffer,
    OrderedDict,
    CodecsEncode,
    ByteArray,
    SetType,
    FrozenSetType,
}

/// An object of the machine. Containers refer to other objects by arena index.
#[derive(Debug)]
enum Obj {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<Id>),
    Tuple(Vec<Id>),
    Dict(Vec<(Id, Id)>),
    Set(Vec<Id>),
    Global(Global),
    Dtype(DType),
    /// `_reconstruct(ndarray, ...)` before its `BUILD`.
    PendingArray,
    NumArray(NpArray),
    ObjectArray {
        shape: Vec<usize>,
        items: Vec<Id>,
    },
}

struct Machine<'a> {
    input: &'a [u8],
    pos: usize,
    /// Offset of the opcode being executed, for messages.
    op_start: usize,
    arena: Vec<Obj>,
    stack: Vec<Id>,
    marks: Vec<usize>,
    memo: HashMap<u64, Id>,
    /// Elements the machine may still copy (argument tuples, array data, dict items): a
    /// memoised large list passed to many calls would otherwise multiply memory.
    work_left: usize,
    work_limit: usize,
    /// Bytes the machine's decoded arrays may take.
    budget: Budget,
}

impl<'a> Machine<'a> {
    fn new(input: &'a [u8], budget: Budget) -> Self {
        let work_limit = input.len().saturating_mul(64).saturating_add(1 << 20);
        Self {
            input,
            pos: 0,
            op_start: 0,
            arena: Vec::new(),
            stack: Vec::new(),
            marks: Vec::new(),
            memo: HashMap::new(),
            work_left: work_limit,
            work_limit,
            budget,
        }
    }

    fn charge(&mut self, elements: usize) -> Result<(), PickleError> {
        self.work_left = self
            .work_left
            .checked_sub(elements)
            .ok_or(PickleError::TooLarge {
                limit: self.work_limit,
            })?;
        Ok(())
    }

    fn malformed(&self, message: impl Into<String>) -> PickleError {
        PickleError::Malformed {
            offset: self.op_start,
            message: message.into(),
        }
    }

    fn unsupported(&self, name: &'static str, why: &'static str) -> PickleError {
        PickleError::Unsupported {
            name,
            offset: self.op_start,
            why,
        }
    }

    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], PickleError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&end| end <= self.input.len())
            .ok_or(PickleError::Truncated {
                what,
                offset: self.pos,
            })?;
        let slice = &self.input[self.pos..end];
        self.pos = end;
        Ok(slice)
    }

    fn u8(&mut self, what: &'static str) -> Result<u8, PickleError> {
        Ok(self.take(1, what)?[0])
    }

    fn le<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], PickleError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, what)?);
        Ok(out)
    }

    /// A length field checked against the remaining input.
    fn length(&mut self, raw: u64, what: &'static str) -> Result<&'a [u8], PickleError> {
        let n = usize::try_from(raw).map_err(|_| PickleError::Truncated {
            what,
            offset: self.pos,
        })?;
        self.take(n, what)
    }

    /// A text line (protocol 0), without its newline.
    fn line(&mut self, what: &'static str) -> Result<&'a [u8], PickleError> {
        let rest = &self.input[self.pos..];
        let n = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or(PickleError::Truncated {
                what,
                offset: self.pos,
            })?;
        self.pos += n + 1;
        Ok(&rest[..n])
    }

    fn text_line(&mut self, what: &'static str) -> Result<&'a str, PickleError> {
        let line = self.line(what)?;
        std::str::from_utf8(line).map_err(|_| self.malformed(format!("{what} is not text")))
    }

    /// The machine's own vectors (objects, stack, memo) may take half the budget: with
    /// the decoded values (charged to the budget) the peak stays within twice the budget.
    fn check_scratch(&self) -> Result<(), PickleError> {
        use std::mem::size_of;
        let scratch = self.arena.capacity() * size_of::<Obj>()
            + (self.stack.capacity() + self.marks.capacity()) * size_of::<Id>()
            + self.memo.capacity() * (size_of::<u64>() + size_of::<Id>());
        if scratch > self.budget.limit() / 2 {
            return Err(PickleError::TooLarge {
                limit: self.budget.limit(),
            });
        }
        Ok(())
    }

    fn alloc(&mut self, obj: Obj) -> Id {
        self.arena.push(obj);
        self.arena.len() - 1
    }

    fn push(&mut self, obj: Obj) {
        let id = self.alloc(obj);
        self.stack.push(id);
    }

    fn pop(&mut self) -> Result<Id, PickleError> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return Err(self.malformed("pop below a MARK"));
        }
        self.stack
            .pop()
            .ok_or_else(|| self.malformed("stack underflow"))
    }

    fn top(&self) -> Result<Id, PickleError> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return Err(self.malformed("stack top is a MARK"));
        }
        self.stack
            .last()
            .copied()
            .ok_or_else(|| self.malformed("empty stack"))
    }

    fn pop_mark(&mut self) -> Result<Vec<Id>, PickleError> {
        let mark = self
            .marks
            .pop()
            .ok_or_else(|| self.malformed("no MARK on the stack"))?;
        Ok(self.stack.split_off(mark))
    }

    fn memo_put(&mut self, index: u64) -> Result<(), PickleError> {
        let top = self.top()?;
        self.memo.insert(index, top);
        Ok(())
    }

    fn memo_get(&mut self, index: u64) -> Result<(), PickleError> {
        let id = *self
            .memo
            .get(&index)
            .ok_or_else(|| self.malformed(format!("memo key {index} was never stored")))?;
        self.stack.push(id);
        Ok(())
    }

    fn text_to_u64(&self, text: &str) -> Result<u64, PickleError> {
        text.trim()
            .parse()
            .map_err(|_| self.malformed(format!("bad memo index {text:?}")))
    }

    fn str_of(&self, id: Id, what: &str) -> Result<&str, PickleError> {
        match &self.arena[id] {
            Obj::Str(s) => Ok(s),
            _ => Err(self.malformed(format!("{what} must be a str"))),
        }
    }

    fn tuple_of(&mut self, id: Id, what: &str) -> Result<Vec<Id>, PickleError> {
        let len = match &self.arena[id] {
            Obj::Tuple(items) | Obj::List(items) => items.len(),
            _ => return Err(self.malformed(format!("{what} must be a tuple"))),
        };
        self.charge(len)?;
        match &self.arena[id] {
            Obj::Tuple(items) | Obj::List(items) => Ok(items.clone()),
            _ => unreachable!("checked above"),
        }
    }

    fn run(&mut self) -> Result<Id, PickleError> {
        loop {
            self.check_scratch()?;
            self.op_start = self.pos;
            let Some(&opcode) = self.input.get(self.pos) else {
                return Err(PickleError::NoStop);
            };
            self.pos += 1;
            match opcode {
                // PROTO
                0x80 => {
                    let version = self.u8("protocol version")?;
                    if version > 5 {
                        return Err(self.malformed(format!("unknown protocol {version}")));
                    }
                }
                // FRAME: framing is only a hint for buffered readers.
                0x95 => {
                    self.le::<8>("frame length")?;
                }
                // STOP
                b'.' => {
                    let root = self.pop()?;
                    return Ok(root);
                }
                b'(' => self.marks.push(self.stack.len()),
                b'0' => {
                    self.pop()?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let top = self.top()?;
                    self.stack.push(top);
                }
                b'N' => self.push(Obj::None),
                0x88 => self.push(Obj::Bool(true)),
                0x89 => self.push(Obj::Bool(false)),
                // Integers.
                b'J' => {
                    let v = i32::from_le_bytes(self.le("BININT")?);
                    self.push(Obj::Int(i64::from(v)));
                }
                b'K' => {
                    let v = self.u8("BININT1")?;
                    self.push(Obj::Int(i64::from(v)));
                }
                b'M' => {
                    let v = u16::from_le_bytes(self.le("BININT2")?);
                    self.push(Obj::Int(i64::from(v)));
                }
                0x8a => {
                    let n = self.u8("LONG1 length")?;
                    let bytes = self.take(usize::from(n), "LONG1")?;
                    let v = self.long_from_le(bytes)?;
                    self.push(Obj::Int(v));
                }
                0x8b => {
                    let n = i32::from_le_bytes(self.le("LONG4 length")?);
                    let n = u64::try_from(n).map_err(|_| self.malformed("negative LONG4 size"))?;
                    let bytes = self.length(n, "LONG4")?;
                    let v = self.long_from_le(bytes)?;
                    self.push(Obj::Int(v));
                }
                b'I' => {
                    let text = self.text_line("INT")?;
                    let obj = match text {
                        "01" => Obj::Bool(true),
                        "00" => Obj::Bool(false),
                        t => Obj::Int(
                            t.trim()
                                .parse()
                                .map_err(|_| self.malformed(format!("bad INT {t:?}")))?,
                        ),
                    };
                    self.push(obj);
                }
                b'L' => {
                    let text = self.text_line("LONG")?;
                    let digits = text.trim().trim_end_matches('L');
                    let v = digits
                        .parse()
                        .map_err(|_| self.malformed(format!("LONG {text:?} does not fit i64")))?;
                    self.push(Obj::Int(v));
                }
                // Floats.
                b'G' => {
                    let v = f64::from_be_bytes(self.le("BINFLOAT")?);
                    self.push(Obj::Float(v));
                }
                b'F' => {
                    let text = self.text_line("FLOAT")?;
                    let v = parse_python_float(text)
                        .ok_or_else(|| self.malformed(format!("bad FLOAT {text:?}")))?;
                    self.push(Obj::Float(v));
                }
                // Strings: unicode.
                b'X' => {
                    let n = u32::from_le_bytes(self.le("BINUNICODE length")?);
                    let s = self.utf8(u64::from(n), "BINUNICODE")?;
                    self.push(Obj::Str(s));
                }
                0x8c => {
                    let n = self.u8("SHORT_BINUNICODE length")?;
                    let s = self.utf8(u64::from(n), "SHORT_BINUNICODE")?;
                    self.push(Obj::Str(s));
                }
                0x8d => {
                    let n = u64::from_le_bytes(self.le("BINUNICODE8 length")?);
                    let s = self.utf8(n, "BINUNICODE8")?;
                    self.push(Obj::Str(s));
                }
                b'V' => {
                    let line = self.line("UNICODE")?;
                    let s = decode_raw_unicode_escape(line)
                        .ok_or_else(|| self.malformed("bad raw-unicode-escape text"))?;
                    self.push(Obj::Str(s));
                }
                // Python 2 `str`: read as latin-1 text, as `encoding='latin1'` does in Python 3.
                b'T' => {
                    let n = i32::from_le_bytes(self.le("BINSTRING length")?);
                    let n =
                        u64::try_from(n).map_err(|_| self.malformed("negative BINSTRING size"))?;
                    let bytes = self.length(n, "BINSTRING")?;
                    self.push(Obj::Str(latin1(bytes)));
                }
                b'U' => {
                    let n = self.u8("SHORT_BINSTRING length")?;
                    let bytes = self.take(usize::from(n), "SHORT_BINSTRING")?;
                    self.push(Obj::Str(latin1(bytes)));
                }
                b'S' => {
                    let line = self.line("STRING")?;
                    let bytes = decode_python_string_literal(line)
                        .ok_or_else(|| self.malformed("bad STRING literal"))?;
                    self.push(Obj::Str(latin1(&bytes)));
                }
                // Bytes.
                b'B' => {
                    let n = u32::from_le_bytes(self.le("BINBYTES length")?);
                    let bytes = self.length(u64::from(n), "BINBYTES")?;
                    self.push(Obj::Bytes(bytes.to_vec()));
                }
                b'C' => {
                    let n = self.u8("SHORT_BINBYTES length")?;
                    let bytes = self.take(usize::from(n), "SHORT_BINBYTES")?;
                    self.push(Obj::Bytes(bytes.to_vec()));
                }
                0x8e => {
                    let n = u64::from_le_bytes(self.le("BINBYTES8 length")?);
                    let bytes = self.length(n, "BINBYTES8")?;
                    self.push(Obj::Bytes(bytes.to_vec()));
                }
                0x96 => {
                    let n = u64::from_le_bytes(self.le("BYTEARRAY8 length")?);
                    let bytes = self.length(n, "BYTEARRAY8")?;
                    self.push(Obj::Bytes(bytes.to_vec()));
                }
                // READONLY_BUFFER: an in-band buffer is already plain bytes.
                0x98 => {
                    self.top()?;
                }
                // Containers.
                b']' => self.push(Obj::List(Vec::new())),
                b'}' => self.push(Obj::Dict(Vec::new())),
                b')' => self.push(Obj::Tuple(Vec::new())),
                0x8f => self.push(Obj::Set(Vec::new())),
                b'l' => {
                    let items = self.pop_mark()?;
                    self.push(Obj::List(items));
                }
                b't' => {
                    let items = self.pop_mark()?;
                    self.push(Obj::Tuple(items));
                }
                0x85..=0x87 => {
                    let n = usize::from(opcode - 0x84);
                    let mut items = Vec::with_capacity(n);
                    for _ in 0..n {
                        items.push(self.pop()?);
                    }
                    items.reverse();
                    self.push(Obj::Tuple(items));
                }
                0x91 => {
                    let items = self.pop_mark()?;
                    self.push(Obj::Set(items));
                }
                b'd' => {
                    let items = self.pop_mark()?;
                    let pairs = self.pairs(items)?;
                    self.push(Obj::Dict(pairs));
                }
                b'a' => {
                    let item = self.pop()?;
                    let list = self.top()?;
                    self.extend_list(list, vec![item])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    let list = self.top()?;
                    self.extend_list(list, items)?;
                }
                0x90 => {
                    let items = self.pop_mark()?;
                    let set = self.top()?;
                    match &mut self.arena[set] {
                        Obj::Set(v) => v.extend(items),
                        _ => return Err(self.malformed("ADDITEMS on a non-set")),
                    }
                }
                b's' => {
                    let value = self.pop()?;
                    let key = self.pop()?;
                    let dict = self.top()?;
                    self.extend_dict(dict, vec![(key, value)])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    let pairs = self.pairs(items)?;
                    let dict = self.top()?;
                    self.extend_dict(dict, pairs)?;
                }
                // Memo.
                b'p' => {
                    let text = self.text_line("PUT")?;
                    let index = self.text_to_u64(text)?;
                    self.memo_put(index)?;
                }
                b'q' => {
                    let index = self.u8("BINPUT")?;
                    self.memo_put(u64::from(index))?;
                }
                b'r' => {
                    let index = u32::from_le_bytes(self.le("LONG_BINPUT")?);
                    self.memo_put(u64::from(index))?;
                }
                0x94 => {
                    let index = self.memo.len() as u64;
                    self.memo_put(index)?;
                }
                b'g' => {
                    let text = self.text_line("GET")?;
                    let index = self.text_to_u64(text)?;
                    self.memo_get(index)?;
                }
                b'h' => {
                    let index = self.u8("BINGET")?;
                    self.memo_get(u64::from(index))?;
                }
                b'j' => {
                    let index = u32::from_le_bytes(self.le("LONG_BINGET")?);
                    self.memo_get(u64::from(index))?;
                }
                // Globals and object construction.
                b'c' => {
                    let module = self.text_line("GLOBAL module")?.to_owned();
                    let name = self.text_line("GLOBAL name")?.to_owned();
                    let global = self.resolve(&module, &name)?;
                    self.push(Obj::Global(global));
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    let module = self.str_of(module, "STACK_GLOBAL module")?.to_owned();
                    let name = self.str_of(name, "STACK_GLOBAL name")?.to_owned();
                    let global = self.resolve(&module, &name)?;
                    self.push(Obj::Global(global));
                }
                b'R' => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let args = self.tuple_of(args, "REDUCE arguments")?;
                    let obj = self.call(callable, &args)?;
                    self.push(obj);
                }
                0x81 => {
                    let args = self.pop()?;
                    let class = self.pop()?;
                    let args = self.tuple_of(args, "NEWOBJ arguments")?;
                    let obj = self.new_object(class, &args)?;
                    self.push(obj);
                }
                0x92 => {
                    let kwargs = self.pop()?;
                    let args = self.pop()?;
                    let class = self.pop()?;
                    if !matches!(&self.arena[kwargs], Obj::Dict(d) if d.is_empty()) {
                        return Err(self.unsupported("NEWOBJ_EX", "keyword arguments"));
                    }
                    let args = self.tuple_of(args, "NEWOBJ_EX arguments")?;
                    let obj = self.new_object(class, &args)?;
                    self.push(obj);
                }
                b'b' => {
                    let state = self.pop()?;
                    let target = self.top()?;
                    self.build(target, state)?;
                }
                b'P' | b'Q' => {
                    return Err(self.unsupported("PERSID", "persistent ids need a host"));
                }
                0x82..=0x84 => {
                    return Err(self.unsupported("EXT", "the extension registry"));
                }
                b'i' | b'o' => {
                    return Err(self.unsupported("INST/OBJ", "old-style class instances"));
                }
                0x97 => {
                    return Err(self.unsupported("NEXT_BUFFER", "out-of-band buffers"));
                }
                other => {
                    return Err(PickleError::UnknownOpcode {
                        opcode: other,
                        offset: self.op_start,
                    });
                }
            }
        }
    }

    fn utf8(&mut self, n: u64, what: &'static str) -> Result<String, PickleError> {
        let bytes = self.length(n, what)?;
        // Python writes surrogates with 'surrogatepass'; replace them rather than fail.
        Ok(String::from_utf8_lossy(bytes).into_owned())
    }

    fn long_from_le(&self, bytes: &[u8]) -> Result<i64, PickleError> {
        if bytes.is_empty() {
            return Ok(0);
        }
        if bytes.len() > 8 {
            // Accept redundant sign-extension bytes.
            let negative = bytes[bytes.len() - 1] & 0x80 != 0;
            let fill = if negative { 0xff } else { 0 };
            let (low, high) = bytes.split_at(8);
            if high.iter().any(|&b| b != fill) || ((low[7] & 0x80 != 0) != negative) {
                return Err(self.malformed("integer does not fit in 64 bits"));
            }
            return Ok(i64::from_le_bytes(low.try_into().expect("eight bytes")));
        }
        let negative = bytes[bytes.len() - 1] & 0x80 != 0;
        let mut full = [if negative { 0xff } else { 0 }; 8];
        full[..bytes.len()].copy_from_slice(bytes);
        Ok(i64::from_le_bytes(full))
    }

    fn pairs(&self, items: Vec<Id>) -> Result<Vec<(Id, Id)>, PickleError> {
        if !items.len().is_multiple_of(2) {
            return Err(self.malformed("odd number of items for a dict"));
        }
        Ok(items.chunks_exact(2).map(|p| (p[0], p[1])).collect())
    }

    fn extend_list(&mut self, list: Id, items: Vec<Id>) -> Result<(), PickleError> {
        match &mut self.arena[list] {
            Obj::List(v) => {
                v.extend(items);
                Ok(())
            }
            _ => Err(self.malformed("APPEND to a non-list")),
        }
    }

    fn extend_dict(&mut self, dict: Id, pairs: Vec<(Id, Id)>) -> Result<(), PickleError> {
        match &mut self.arena[dict] {
            Obj::Dict(v) => {
                // Python dicts keep the first insertion position and the last value.
                for (k, val) in pairs {
                    v.push((k, val));
                }
                Ok(())
            }
            _ => Err(self.malformed("SETITEM on a non-dict")),
        }
    }

    fn resolve(&self, module: &str, name: &str) -> Result<Global, PickleError> {
        let numpy_core = |suffix: &str| {
            module == format!("numpy.core.{suffix}") || module == format!("numpy._core.{suffix}")
        };
        let global = match name {
            "_reconstruct" if numpy_core("multiarray") => Some(Global::Reconstruct),
            "scalar" if numpy_core("multiarray") => Some(Global::Scalar),
            "_frombuffer" if numpy_core("numeric") => Some(Global::FromBuffer),
            "ndarray" if module == "numpy" => Some(Global::NdarrayType),
            "dtype" if module == "numpy" => Some(Global::DtypeType),
            "OrderedDict" if module == "collections" => Some(Global::OrderedDict),
            "encode" if module == "_codecs" => Some(Global::CodecsEncode),
            // Protocols 0-2 write an empty `bytes` as `bytes()`.
            "bytearray" | "bytes" if is_builtins(module) => Some(Global::ByteArray),
            "set" if is_builtins(module) => Some(Global::SetType),
            "frozenset" if is_builtins(module) => Some(Global::FrozenSetType),
            _ => None,
        };
        global.ok_or_else(|| {
            let hint = if module.starts_with("chumpy") {
                " (chumpy objects appear in original SMPL .pkl files: convert the model to a \
                 dense .npz with numpy arrays)"
            } else if module.starts_with("scipy") {
                " (scipy sparse matrices appear in original SMPL .pkl files: convert the model \
                 to a dense .npz)"
            } else {
                ""
            };
            PickleError::ForbiddenGlobal {
                module: module.to_owned(),
                name: name.to_owned(),
                offset: self.op_start,
                hint,
            }
        })
    }

    fn global_of(&self, id: Id) -> Result<Global, PickleError> {
        match &self.arena[id] {
            Obj::Global(g) => Ok(*g),
            _ => Err(self.malformed("REDUCE on something that is not a known callable")),
        }
    }

    fn new_object(&mut self, class: Id, args: &[Id]) -> Result<Obj, PickleError> {
        match self.global_of(class)? {
            Global::OrderedDict if args.is_empty() => Ok(Obj::Dict(Vec::new())),
            Global::SetType | Global::FrozenSetType if args.is_empty() => Ok(Obj::Set(Vec::new())),
            _ => Err(self.malformed("NEWOBJ of a class this reader does not construct")),
        }
    }

    /// `REDUCE`: interprets calls to the allowed globals.
    fn call(&mut self, callable: Id, args: &[Id]) -> Result<Obj, PickleError> {
        match self.global_of(callable)? {
            Global::Reconstruct => {
                // _reconstruct(ndarray, (0,), b'b'): an empty array that BUILD fills.
                match args.first().map(|&a| &self.arena[a]) {
                    Some(Obj::Global(Global::NdarrayType)) => Ok(Obj::PendingArray),
                    _ => Err(self.malformed("_reconstruct of something other than ndarray")),
                }
            }
            Global::DtypeType => {
                let descr = args
                    .first()
                    .ok_or_else(|| self.malformed("dtype() without arguments"))?;
                let descr = self.str_of(*descr, "dtype argument")?;
                let dtype = DType::parse(descr).map_err(|m| self.malformed(m))?;
                Ok(Obj::Dtype(dtype))
            }
            Global::Scalar => {
                let [dtype, payload] = args else {
                    return Err(self.malformed("scalar() needs (dtype, data)"));
                };
                let dtype = self.dtype_of(*dtype)?;
                if dtype.kind == Kind::Object {
                    return Err(self.malformed("object scalars are not supported"));
                }
                let bytes = self.raw_bytes(*payload)?;
                let data = dtype.decode(&bytes, 1).map_err(|m| self.malformed(m))?;
                Ok(scalar_obj(data))
            }
            Global::FromBuffer => {
                let [buffer, dtype, shape, order] = args else {
                    return Err(self.malformed("_frombuffer() needs (buffer, dtype, shape, order)"));
                };
                let dtype = self.dtype_of(*dtype)?;
                let shape = self.shape_of(*shape)?;
                let fortran = match self.str_of(*order, "_frombuffer order")? {
                    "C" => false,
                    "F" => true,
                    other => return Err(self.malformed(format!("unknown order {other:?}"))),
                };
                let bytes = self.raw_bytes(*buffer)?;
                let array = self.numeric_array(&dtype, shape, fortran, &bytes)?;
                Ok(Obj::NumArray(array))
            }
            Global::OrderedDict => match args {
                [] => Ok(Obj::Dict(Vec::new())),
                [items] => {
                    let items = self.tuple_of(*items, "OrderedDict items")?;
                    let mut pairs = Vec::with_capacity(items.len());
                    for item in items {
                        let pair = self.tuple_of(item, "OrderedDict item")?;
                        let [k, v] = pair[..] else {
                            return Err(self.malformed("OrderedDict item is not a pair"));
                        };
                        pairs.push((k, v));
                    }
                    Ok(Obj::Dict(pairs))
                }
                _ => Err(self.malformed("OrderedDict() with several arguments")),
            },
            Global::CodecsEncode => {
                // Protocol 0-2 writes bytes as _codecs.encode(text, 'latin1').
                let text = args
                    .first()
                    .ok_or_else(|| self.malformed("encode() without arguments"))?;
                let text = self.str_of(*text, "encode text")?;
                let encoding = match args.get(1) {
                    Some(&e) => self.str_of(e, "encoding")?.to_ascii_lowercase(),
                    None => "utf-8".to_owned(),
                };
                let bytes = match encoding.as_str() {
                    "latin1" | "latin-1" | "iso-8859-1" => {
                        latin1_encode(text).ok_or_else(|| self.malformed("text is not latin-1"))?
                    }
                    "utf-8" | "utf8" => text.as_bytes().to_vec(),
                    other => return Err(self.malformed(format!("unknown encoding {other:?}"))),
                };
                Ok(Obj::Bytes(bytes))
            }
            Global::ByteArray => match args {
                [] => Ok(Obj::Bytes(Vec::new())),
                [b] => match &self.arena[*b] {
                    Obj::Bytes(_) => Ok(Obj::Bytes(self.raw_bytes(*b)?)),
                    _ => Err(self.malformed("bytearray() of a non-bytes value")),
                },
                _ => Err(self.malformed("bytearray() with several arguments")),
            },
            Global::SetType | Global::FrozenSetType => match args {
                [] => Ok(Obj::Set(Vec::new())),
                [items] => Ok(Obj::Set(self.tuple_of(*items, "set items")?)),
                _ => Err(self.malformed("set() with several arguments")),
            },
            Global::NdarrayType => Err(self.malformed("ndarray() cannot be called directly")),
        }
    }

    /// `BUILD`: sets the state of a pending array or a dtype.
    fn build(&mut self, target: Id, state: Id) -> Result<(), PickleError> {
        match &self.arena[target] {
            Obj::Dtype(_) => {
                // (version, byteorder, subarray, names, fields, elsize, alignment, flags[, metadata])
                let items = self.tuple_of(state, "dtype state")?;
                if items.len() < 8 {
                    return Err(self.malformed("dtype state is too short"));
                }
                if !matches!(self.arena[items[2]], Obj::None)
                    || !matches!(self.arena[items[3]], Obj::None)
                {
                    return Err(self.malformed("structured and subarray dtypes are not supported"));
                }
                let order = self.str_of(items[1], "dtype byte order")?;
                let big = order == ">" || order == "!";
                if let Obj::Dtype(d) = &mut self.arena[target] {
                    d.big_endian = big && d.itemsize > 1 && d.kind != Kind::Bytes;
                }
                Ok(())
            }
            Obj::PendingArray => {
                let items = self.tuple_of(state, "ndarray state")?;
                // (version, shape, dtype, is_fortran, rawdata) or the older 4-tuple.
                let items = match items.len() {
                    5 => &items[1..],
                    4 => &items[..],
                    _ => return Err(self.malformed("ndarray state has the wrong length")),
                };
                let shape = self.shape_of(items[0])?;
                let dtype = self.dtype_of(items[1])?;
                let fortran = match &self.arena[items[2]] {
                    Obj::Bool(b) => *b,
                    Obj::Int(i) => *i != 0,
                    _ => return Err(self.malformed("is_fortran must be a bool")),
                };
                let obj = if dtype.kind == Kind::Object {
                    if !matches!(&self.arena[items[3]], Obj::List(_)) {
                        return Err(self.malformed("object array data must be a list"));
                    }
                    let list = self.tuple_of(items[3], "object array data")?;
                    let count = checked_product(&shape)
                        .ok_or_else(|| self.malformed("array shape overflows"))?;
                    if count != list.len() {
                        return Err(self.malformed(format!(
                            "object array of shape {shape:?} has {} items",
                            list.len()
                        )));
                    }
                    let items = if fortran {
                        fortran_to_c(&list, &shape)
                    } else {
                        list
                    };
                    Obj::ObjectArray { shape, items }
                } else {
                    let bytes = self.raw_bytes(items[3])?;
                    Obj::NumArray(self.numeric_array(&dtype, shape, fortran, &bytes)?)
                };
                self.arena[target] = obj;
                Ok(())
            }
            Obj::Dict(_) => {
                // Instance __dict__ updates are not needed for the datasets; refuse clearly.
                Err(self.unsupported("BUILD", "object state on a dict"))
            }
            _ => Err(self.malformed("BUILD on an object without state")),
        }
    }

    fn dtype_of(&self, id: Id) -> Result<DType, PickleError> {
        match &self.arena[id] {
            Obj::Dtype(d) => Ok(d.clone()),
            _ => Err(self.malformed("expected a numpy dtype")),
        }
    }

    fn shape_of(&mut self, id: Id) -> Result<Vec<usize>, PickleError> {
        let items = self.tuple_of(id, "array shape")?;
        items
            .iter()
            .map(|&i| match self.arena[i] {
                Obj::Int(n) => usize::try_from(n).map_err(|_| self.malformed("negative dimension")),
                _ => Err(self.malformed("array dimensions must be integers")),
            })
            .collect()
    }

    /// Array data: bytes, or text holding latin-1 bytes (Python 2 pickles read as latin-1).
    fn raw_bytes(&mut self, id: Id) -> Result<Vec<u8>, PickleError> {
        let len = match &self.arena[id] {
            Obj::Bytes(b) => b.len(),
            Obj::Str(s) => s.len(),
            _ => 0,
        };
        self.charge(len)?;
        match &self.arena[id] {
            Obj::Bytes(b) => Ok(b.clone()),
            Obj::Str(s) => {
                latin1_encode(s).ok_or_else(|| self.malformed("array data is not latin-1"))
            }
            _ => Err(self.malformed("array data must be bytes")),
        }
    }

    fn numeric_array(
        &mut self,
        dtype: &DType,
        shape: Vec<usize>,
        fortran: bool,
        bytes: &[u8],
    ) -> Result<NpArray, PickleError> {
        match numeric_array(dtype, shape, fortran, bytes, &mut self.budget) {
            Ok(array) => Ok(array),
            Err(ArrayError::OverBudget(OverBudget { limit })) => {
                Err(PickleError::TooLarge { limit })
            }
            Err(ArrayError::Invalid(message)) => Err(self.malformed(message)),
        }
    }
}

/// Why [`numeric_array`] refused.
pub(crate) enum ArrayError {
    Invalid(String),
    OverBudget(OverBudget),
}

/// Builds a numeric array from raw bytes, checking the size and charging the decoded bytes
/// (twice for a Fortran-order reorder, which copies) to `budget` before decoding.
pub(crate) fn numeric_array(
    dtype: &DType,
    shape: Vec<usize>,
    fortran: bool,
    bytes: &[u8],
    budget: &mut Budget,
) -> Result<NpArray, ArrayError> {
    let invalid = |m: &str| ArrayError::Invalid(m.to_owned());
    let count = checked_product(&shape).ok_or_else(|| invalid("array shape overflows"))?;
    let copies = if fortran && shape.len() > 1 { 2 } else { 1 };
    let decoded = dtype
        .decoded_bytes(count)
        .and_then(|n| n.checked_mul(copies))
        .ok_or_else(|| invalid("array shape overflows"))?;
    budget.charge(decoded).map_err(ArrayError::OverBudget)?;
    let data = dtype.decode(bytes, count).map_err(ArrayError::Invalid)?;
    let data = if fortran && shape.len() > 1 {
        reorder_fortran(data, &shape)
    } else {
        data
    };
    Ok(NpArray {
        dtype: dtype.descr(),
        shape,
        data,
    })
}

pub(crate) fn checked_product(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d))
}

/// Reorders elements stored in Fortran (column-major) order into C order.
pub(crate) fn fortran_to_c<T: Clone>(items: &[T], shape: &[usize]) -> Vec<T> {
    let count = items.len();
    if shape.len() < 2 || count == 0 {
        return items.to_vec();
    }
    let mut out = Vec::with_capacity(count);
    let mut index = vec![0usize; shape.len()];
    for _ in 0..count {
        // Column-major offset of the C-order multi-index.
        let mut offset = 0;
        let mut stride = 1;
        for (i, &d) in index.iter().zip(shape) {
            offset += i * stride;
            stride *= d;
        }
        out.push(items[offset].clone());
        for axis in (0..shape.len()).rev() {
            index[axis] += 1;
            if index[axis] < shape[axis] {
                break;
            }
            index[axis] = 0;
        }
    }
    out
}

fn reorder_fortran(data: ArrayData, shape: &[usize]) -> ArrayData {
    match data {
        ArrayData::Bool(v) => ArrayData::Bool(fortran_to_c(&v, shape)),
        ArrayData::U8(v) => ArrayData::U8(fortran_to_c(&v, shape)),
        ArrayData::I64(v) => ArrayData::I64(fortran_to_c(&v, shape)),
        ArrayData::U64(v) => ArrayData::U64(fortran_to_c(&v, shape)),
        ArrayData::F32(v) => ArrayData::F32(fortran_to_c(&v, shape)),
        ArrayData::F64(v) => ArrayData::F64(fortran_to_c(&v, shape)),
        ArrayData::Str(v) => ArrayData::Str(fortran_to_c(&v, shape)),
        ArrayData::Bytes(v) => ArrayData::Bytes(fortran_to_c(&v, shape)),
        ArrayData::Object(v) => ArrayData::Object(fortran_to_c(&v, shape)),
    }
}

fn scalar_obj(data: ArrayData) -> Obj {
    match data {
        ArrayData::Bool(v) => Obj::Bool(v[0]),
        ArrayData::U8(v) => Obj::Int(i64::from(v[0])),
        ArrayData::I64(v) => Obj::Int(v[0]),
        ArrayData::U64(v) => match i64::try_from(v[0]) {
            Ok(i) => Obj::Int(i),
            Err(_) => Obj::Float(v[0] as f64),
        },
        ArrayData::F32(v) => Obj::Float(f64::from(v[0])),
        ArrayData::F64(v) => Obj::Float(v[0]),
        ArrayData::Str(mut v) => Obj::Str(v.swap_remove(0)),
        ArrayData::Bytes(mut v) => Obj::Bytes(v.swap_remove(0)),
        ArrayData::Object(_) => Obj::None,
    }
}

fn is_builtins(module: &str) -> bool {
    module == "builtins" || module == "__builtin__"
}

fn latin1(bytes: &[u8]) -> String {
    bytes.iter().map(|&b| char::from(b)).collect()
}

fn latin1_encode(text: &str) -> Option<Vec<u8>> {
    text.chars()
        .map(|c| u8::try_from(u32::from(c)).ok())
        .collect()
}

fn parse_python_float(text: &str) -> Option<f64> {
    match text.trim() {
        "inf" => Some(f64::INFINITY),
        "-inf" => Some(f64::NEG_INFINITY),
        "nan" => Some(f64::NAN),
        t => t.parse().ok(),
    }
}

/// Python's `raw-unicode-escape`: latin-1 bytes with `\uXXXX` and `\UXXXXXXXX` escapes.
fn decode_raw_unicode_escape(bytes: &[u8]) -> Option<String> {
    let mut out = String::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'\\' && i + 1 < bytes.len() && matches!(bytes[i + 1], b'u' | b'U') {
            let digits = if bytes[i + 1] == b'u' { 4 } else { 8 };
            let hex = bytes.get(i + 2..i + 2 + digits)?;
            let code = u32::from_str_radix(std::str::from_utf8(hex).ok()?, 16).ok()?;
            out.push(char::from_u32(code)?);
            i += 2 + digits;
        } else {
            out.push(char::from(bytes[i]));
            i += 1;
        }
    }
    Some(out)
}

/// A Python 2 `repr` string literal (`'...'` or `"..."`) to its bytes.
fn decode_python_string_literal(line: &[u8]) -> Option<Vec<u8>> {
    let (&quote, rest) = line.split_first()?;
    if quote != b'\'' && quote != b'"' {
        return None;
    }
    let (&last, body) = rest.split_last()?;
    if last != quote {
        return None;
    }
    let mut out = Vec::with_capacity(body.len());
    let mut i = 0;
    while i < body.len() {
        let b = body[i];
        i += 1;
        if b != b'\\' {
            out.push(b);
            continue;
        }
        let &e = body.get(i)?;
        i += 1;
        match e {
            b'n' => out.push(b'\n'),
            b't' => out.push(b'\t'),
            b'r' => out.push(b'\r'),
            b'a' => out.push(7),
            b'b' => out.push(8),
            b'f' => out.push(12),
            b'v' => out.push(11),
            b'\\' | b'\'' | b'"' => out.push(e),
            b'x' => {
                let hex = body.get(i..i + 2)?;
                out.push(u8::from_str_radix(std::str::from_utf8(hex).ok()?, 16).ok()?);
                i += 2;
            }
            b'0'..=b'7' => {
                let mut value = u32::from(e - b'0');
                let mut n = 1;
                while n < 3 && i < body.len() && (b'0'..=b'7').contains(&body[i]) {
                    value = value * 8 + u32::from(body[i] - b'0');
                    i += 1;
                    n += 1;
                }
                out.push(u8::try_from(value).ok()?);
            }
            other => {
                out.push(b'\\');
                out.push(other);
            }
        }
    }
    Some(out)
}

#[derive(Hash, PartialEq, Eq)]
enum KeyRepr {
    Str(String),
    Int(i64),
    Bytes(Vec<u8>),
}

/// Turns arena objects into an owned [`Value`] tree within a size budget.
struct Builder<'a> {
    arena: &'a [Obj],
    budget: Budget,
    in_progress: Vec<bool>,
}

impl Builder<'_> {
    fn charge(&mut self, bytes: usize) -> Result<(), PickleError> {
        self.budget
            .charge(bytes.max(1))
            .map_err(|OverBudget { limit }| PickleError::TooLarge { limit })
    }

    fn build(&mut self, id: Id, depth: usize) -> Result<Value, PickleError> {
        if depth > MAX_DEPTH || self.in_progress[id] {
            return Err(PickleError::TooDeep { limit: MAX_DEPTH });
        }
        self.charge(std::mem::size_of::<Value>())?;
        self.in_progress[id] = true;
        let arena = self.arena;
        let value = match &arena[id] {
            Obj::None => Value::None,
            Obj::Bool(b) => Value::Bool(*b),
            Obj::Int(i) => Value::Int(*i),
            Obj::Float(f) => Value::Float(*f),
            Obj::Str(s) => {
                self.charge(s.len())?;
                Value::Str(s.clone())
            }
            Obj::Bytes(b) => {
                self.charge(b.len())?;
                Value::Bytes(b.clone())
            }
            Obj::List(items) => Value::List(self.build_all(items, depth)?),
            Obj::Tuple(items) => Value::Tuple(self.build_all(items, depth)?),
            Obj::Set(items) => Value::Set(self.build_all(items, depth)?),
            Obj::Dict(pairs) => {
                let mut out: Vec<(Value, Value)> = Vec::with_capacity(pairs.len());
                // Position of each string or integer key, so repeated keys replace the value
                // in place as in Python without a quadratic scan.
                let mut positions: HashMap<KeyRepr, usize> = HashMap::new();
                for &(k, v) in pairs {
                    let key = self.build(k, depth + 1)?;
                    let value = self.build(v, depth + 1)?;
                    let repr = match &key {
                        Value::Str(s) => Some(KeyRepr::Str(s.clone())),
                        Value::Int(i) => Some(KeyRepr::Int(*i)),
                        Value::Bytes(b) => Some(KeyRepr::Bytes(b.clone())),
                        _ => None,
                    };
                    match repr {
                        Some(repr) => match positions.get(&repr) {
                            Some(&at) => out[at].1 = value,
                            None => {
                                positions.insert(repr, out.len());
                                out.push((key, value));
                            }
                        },
                        None => out.push((key, value)),
                    }
                }
                Value::Dict(out)
            }
            Obj::NumArray(array) => {
                self.charge(array.data.footprint())?;
                Value::Array(array.clone())
            }
            Obj::ObjectArray { shape, items } => Value::Array(NpArray {
                dtype: "|O".to_owned(),
                shape: shape.clone(),
                data: ArrayData::Object(self.build_all(items, depth)?),
            }),
            Obj::Global(_) | Obj::Dtype(_) | Obj::PendingArray => {
                return Err(PickleError::Malformed {
                    offset: 0,
                    message: "the pickle holds a bare type, dtype or unfinished array".to_owned(),
                });
            }
        };
        self.in_progress[id] = false;
        Ok(value)
    }

    fn build_all(&mut self, items: &[Id], depth: usize) -> Result<Vec<Value>, PickleError> {
        items.iter().map(|&i| self.build(i, depth + 1)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn protocol_two_dict_of_scalars() {
        // pickle.dumps({'a': 1, 'b': [2.5, None, True]}, protocol=2)
        let bytes = b"\x80\x02}q\x00(X\x01\x00\x00\x00aq\x01K\x01X\x01\x00\x00\x00bq\x02]q\x03(G@\x04\x00\x00\x00\x00\x00\x00N\x88eu.";
        let v = load(bytes).unwrap();
        assert_eq!(v.get("a"), Some(&Value::Int(1)));
        assert_eq!(
            v.get("b"),
            Some(&Value::List(vec![
                Value::Float(2.5),
                Value::None,
                Value::Bool(true)
            ]))
        );
    }

    #[test]
    fn protocol_zero_text_opcodes() {
        // pickle.dumps({'k': (1, 'x\u00e9', -3.5, 10**12)}, protocol=0)
        let bytes = b"(dp0\nVk\np1\n(I1\nVx\xe9\np2\nF-3.5\nL1000000000000L\ntp3\ns.";
        let v = load(bytes).unwrap();
        assert_eq!(
            v.get("k"),
            Some(&Value::Tuple(vec![
                Value::Int(1),
                Value::Str("x\u{e9}".into()),
                Value::Float(-3.5),
                Value::Int(1_000_000_000_000),
            ]))
        );
    }

    #[test]
    fn memo_shares_mutations() {
        // A list memoised while empty, filled afterwards, then referenced again:
        // x = []; pickle.dumps([x, x]) where x gets an element after memoisation.
        let bytes = b"\x80\x04]\x94(]\x94K\x07ah\x01e.";
        let v = load(bytes).unwrap();
        let seven = Value::List(vec![Value::Int(7)]);
        assert_eq!(v, Value::List(vec![seven.clone(), seven]));
    }

    #[test]
    fn cycles_and_deep_nesting_are_rejected() {
        // l = []; l.append(l)
        let cyclic = b"\x80\x04]\x94h\x00a.";
        assert_eq!(load(cyclic), Err(PickleError::TooDeep { limit: MAX_DEPTH }));
        let mut deep = vec![0x80, 4];
        deep.extend(std::iter::repeat_n(b']', 1000));
        deep.extend(std::iter::repeat_n(b'a', 999));
        deep.push(b'.');
        assert_eq!(load(&deep), Err(PickleError::TooDeep { limit: MAX_DEPTH }));
    }

    #[test]
    fn exponential_sharing_hits_the_budget() {
        // x0 = []; x(i+1) = [xi, xi] twenty-five times: 2^25 nodes from a few hundred bytes.
        let mut bytes = vec![0x80, 4, b']', 0x94];
        for i in 0..60u8 {
            bytes.extend([b'h', i, b'h', i, 0x86, 0x94]);
        }
        bytes.push(b'.');
        assert!(matches!(load(&bytes), Err(PickleError::TooLarge { .. })));
    }

    #[test]
    fn forbidden_globals_name_the_callable() {
        // pickle.dumps(os.system) style GLOBAL.
        let bytes = b"cos\nsystem\n(S'echo hi'\ntR.";
        match load(bytes) {
            Err(PickleError::ForbiddenGlobal { module, name, .. }) => {
                assert_eq!((module.as_str(), name.as_str()), ("os", "system"));
            }
            other => panic!("expected a forbidden global, got {other:?}"),
        }
        let chumpy = b"cchumpy.ch\nCh\n.";
        let message = load(chumpy).unwrap_err().to_string();
        assert!(message.contains("dense .npz"), "{message}");
    }

    #[test]
    fn lengths_beyond_the_input_are_truncation_errors() {
        let huge = b"\x80\x04\x8e\xff\xff\xff\xff\xff\xff\xff\x7f.";
        assert!(matches!(load(huge), Err(PickleError::Truncated { .. })));
        let long4 = b"\x8b\xff\xff\xff\x7f";
        assert!(matches!(load(long4), Err(PickleError::Truncated { .. })));
        assert_eq!(load(b""), Err(PickleError::NoStop));
        assert_eq!(load(b"N"), Err(PickleError::NoStop));
    }

    #[test]
    fn long_integers_decode_twos_complement() {
        // LONG1 with 2 bytes 0xff7f = 32767; 0x0080 = -32768 (little endian).
        let v = load(b"\x8a\x02\xff\x7f.").unwrap();
        assert_eq!(v, Value::Int(32767));
        let v = load(b"\x8a\x02\x00\x80.").unwrap();
        assert_eq!(v, Value::Int(-32768));
        let v = load(b"\x8a\x09\xff\xff\xff\xff\xff\xff\xff\xff\xff.").unwrap();
        assert_eq!(v, Value::Int(-1));
        assert!(load(b"\x8a\x09\x00\x00\x00\x00\x00\x00\x00\x00\x01.").is_err());
    }

    #[test]
    fn string_literals_unescape() {
        assert_eq!(
            decode_python_string_literal(b"'a\\x41\\n\\101\\\\'").unwrap(),
            b"aA\nA\\".to_vec()
        );
        assert_eq!(decode_python_string_literal(b"'abc"), None);
        assert_eq!(
            decode_raw_unicode_escape(b"a\\u00e9\\U0001F600").unwrap(),
            "a\u{e9}\u{1F600}"
        );
    }

    #[test]
    fn fortran_order_is_converted() {
        // Shape (2, 3) stored column-major: columns (0, 3), (1, 4), (2, 5).
        let stored = [0, 3, 1, 4, 2, 5];
        assert_eq!(fortran_to_c(&stored, &[2, 3]), vec![0, 1, 2, 3, 4, 5]);
        // (2, 2, 2): element [i][j][k] at offset i + 2j + 4k.
        let stored: Vec<usize> = (0..8).collect();
        let c = fortran_to_c(&stored, &[2, 2, 2]);
        assert_eq!(c, vec![0, 4, 2, 6, 1, 5, 3, 7]);
    }
}
