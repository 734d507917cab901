//! Reading and writing `.npy` arrays, and the small Python-literal parser their headers need.
//!
//! The reader is strict and self-contained (it never allocates from a size the file claims
//! before checking the bytes are there, and never panics on a hostile header): magic and
//! version 1/2/3, a `{'descr': ..., 'fortran_order': ..., 'shape': (...)}` header, then exactly
//! `prod(shape) · itemsize` data bytes. C and Fortran order and both endiannesses are read;
//! the writer (npyz) always writes little-endian C order.

use std::path::Path;

use crate::error::{DataError, Result, format_err};

/// A parsed `.npy` array borrowing its data bytes.
#[derive(Debug)]
pub(crate) struct NpyArray<'a> {
    pub(crate) shape: Vec<usize>,
    fortran_order: bool,
    dtype: NpyDtype,
    /// The descr string as written, for error messages.
    descr: String,
    data: &'a [u8],
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct NpyDtype {
    kind: u8,
    size: usize,
    big_endian: bool,
}

/// Largest `.npy` header read (numpy writes a few hundred bytes).
pub const MAX_NPY_HEADER_BYTES: usize = 1 << 20;

/// Largest data of one array (`prod(shape) · itemsize`, 2 GiB): an archive entry is read only
/// up to the size its header declares, and a header declaring more is refused before anything
/// is decompressed.
pub const MAX_ARRAY_BYTES: usize = 1 << 31;

/// Reads one `.npy` stream (an archive entry or a file), never more than its header declares:
/// the fixed prefix, the header (at most [`MAX_NPY_HEADER_BYTES`]), then the declared data
/// (at most [`MAX_ARRAY_BYTES`]) and one byte more, so that excess data is reported by
/// [`NpyArray::parse`] without being decompressed. Malformed prefixes are returned as read
/// for `parse` to report.
pub(crate) fn read_bounded(
    r: &mut impl std::io::Read,
    path: &Path,
    array: &str,
) -> Result<Vec<u8>> {
    use std::io::Read;
    let bad = |reason: String| format_err(path, format!("array `{array}`: {reason}"));
    let io = |e: std::io::Error| crate::error::archive_err(path, Some(array))(e);
    let mut buf = Vec::new();
    r.by_ref().take(12).read_to_end(&mut buf).map_err(io)?;
    if buf.len() < 10 || &buf[..6] != b"\x93NUMPY" {
        return Ok(buf);
    }
    let (header_len, start) = match buf[6] {
        1 => (u16::from_le_bytes([buf[8], buf[9]]) as usize, 10),
        2 | 3 if buf.len() >= 12 => {
            (u32::from_le_bytes([buf[8], buf[9], buf[10], buf[11]]) as usize, 12)
        }
        _ => return Ok(buf),
    };
    if header_len > MAX_NPY_HEADER_BYTES {
        return Err(bad(format!(
            "header of {header_len} bytes, more than the limit of {MAX_NPY_HEADER_BYTES}"
        )));
    }
    let header_end = start + header_len;
    let more = header_end.saturating_sub(buf.len()) as u64;
    r.by_ref().take(more).read_to_end(&mut buf).map_err(io)?;
    let nbytes = header(&buf, path, array)?.nbytes.unwrap_or(0);
    let total = header_end + nbytes;
    let more = (total + 1).saturating_sub(buf.len()) as u64;
    r.by_ref().take(more).read_to_end(&mut buf).map_err(io)?;
    Ok(buf)
}

/// What an `.npy` header says.
struct Header {
    shape: Vec<usize>,
    fortran_order: bool,
    dtype: Option<NpyDtype>,
    descr: String,
    header_end: usize,
    /// The data bytes the shape and a known dtype need.
    nbytes: Option<usize>,
}

/// Parses the prefix and header of an `.npy` file (the data need not be there).
fn header(bytes: &[u8], path: &Path, array: &str) -> Result<Header> {
    let bad = |reason: String| format_err(path, format!("array `{array}`: {reason}"));
    const MAGIC: &[u8] = b"\x93NUMPY";
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(bad("not an .npy file (bad magic)".into()));
    }
    let major = bytes[6];
    let (header_len, start): (usize, usize) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => {
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        _ => return Err(bad(format!("unsupported .npy format version {major}"))),
    };
    let header_end = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| bad("truncated header".into()))?;
    let header = std::str::from_utf8(&bytes[start..header_end])
        .map_err(|_| bad("header is not valid text".into()))?;
    let dict = match PyValue::parse(header).map_err(|e| bad(format!("bad header: {e}")))? {
        PyValue::Dict(d) => d,
        _ => return Err(bad("header is not a dict".into())),
    };
    let get = |key: &str| {
        dict.iter()
            .find(|(k, _)| matches!(k, PyValue::Str(s) if s == key))
            .map(|(_, v)| v)
            .ok_or_else(|| bad(format!("header has no `{key}`")))
    };
    let descr = match get("descr")? {
        PyValue::Str(s) => s.clone(),
        other => {
            return Err(DataError::Dtype {
                path: path.to_owned(),
                array: array.to_owned(),
                found: format!("{other:?}"),
                expected: "a plain numeric dtype, not a structured one",
            });
        }
    };
    let fortran_order = match get("fortran_order")? {
        PyValue::Bool(b) => *b,
        _ => return Err(bad("`fortran_order` is not a bool".into())),
    };
    let shape = match get("shape")? {
        PyValue::Tuple(items) => items
            .iter()
            .map(|v| match v {
                PyValue::Int(n) => usize::try_from(*n).map_err(|_| bad("shape too large".into())),
                _ => Err(bad("`shape` holds a non-integer".into())),
            })
            .collect::<Result<Vec<usize>>>()?,
        _ => return Err(bad("`shape` is not a tuple".into())),
    };
    let dtype = NpyDtype::parse(&descr);
    let count = shape
        .iter()
        .try_fold(1usize, |acc, &s| acc.checked_mul(s))
        .ok_or_else(|| bad(format!("shape {shape:?} overflows")))?;
    let nbytes = match dtype {
        Some(dtype) => Some(
            count.checked_mul(dtype.size).filter(|&n| n <= MAX_ARRAY_BYTES).ok_or_else(|| {
                bad(format!(
                    "shape {shape:?} of `{descr}` needs more than the limit of \
                         {MAX_ARRAY_BYTES} data bytes"
                ))
            })?,
        ),
        None => None,
    };
    Ok(Header { shape, fortran_order, dtype, descr, header_end, nbytes })
}

impl<'a> NpyArray<'a> {
    /// Parses the bytes of one `.npy` file. `path` and `array` only label errors.
    pub(crate) fn parse(bytes: &'a [u8], path: &Path, array: &str) -> Result<Self> {
        let bad = |reason: String| format_err(path, format!("array `{array}`: {reason}"));
        let Header { shape, fortran_order, dtype, descr, header_end, nbytes } =
            header(bytes, path, array)?;
        let data = &bytes[header_end..];
        if let Some(nbytes) = nbytes {
            if data.len() != nbytes {
                return Err(bad(format!(
                    "shape {shape:?} of `{descr}` needs {nbytes} data bytes, the file has {}",
                    data.len()
                )));
            }
        }
        // An unparsable descr is reported as a dtype error by the decoders (with the role the
        // array plays), so keep a placeholder kind that no decoder accepts.
        let dtype = dtype.unwrap_or(NpyDtype { kind: 0, size: 0, big_endian: false });
        Ok(Self { shape, fortran_order, dtype, descr, data })
    }

    fn dtype_err(&self, path: &Path, array: &str, expected: &'static str) -> DataError {
        DataError::Dtype {
            path: path.to_owned(),
            array: array.to_owned(),
            found: self.descr.clone(),
            expected,
        }
    }

    /// The values as `f32` in C order; `float32` and `float64` accepted (`float64` is rounded
    /// to nearest, values beyond the `f32` range become infinite and are caught downstream).
    pub(crate) fn to_f32(&self, path: &Path, array: &str) -> Result<Vec<f32>> {
        const EXPECTED: &str = "float32 or float64";
        let NpyDtype { kind, size, big_endian } = self.dtype;
        if kind != b'f' {
            return Err(self.dtype_err(path, array, EXPECTED));
        }
        let values: Vec<f32> = match size {
            4 => self
                .data
                .chunks_exact(4)
                .map(|c| {
                    let b = [c[0], c[1], c[2], c[3]];
                    if big_endian { f32::from_be_bytes(b) } else { f32::from_le_bytes(b) }
                })
                .collect(),
            8 => self
                .data
                .chunks_exact(8)
                .map(|c| {
                    let b = [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
                    (if big_endian { f64::from_be_bytes(b) } else { f64::from_le_bytes(b) }) as f32
                })
                .collect(),
            _ => return Err(self.dtype_err(path, array, EXPECTED)),
        };
        Ok(self.to_c_order(values))
    }

    /// The values as mask flags in C order: bool, integer or float arrays holding only 0 and 1.
    /// Other values are reported as `Err((flat C-order index, value as text))`.
    pub(crate) fn to_mask(
        &self,
        path: &Path,
        array: &str,
    ) -> Result<Result<Vec<bool>, (usize, String)>> {
        const EXPECTED: &str = "bool, integer or float (holding 0 and 1)";
        let NpyDtype { kind, size, big_endian } = self.dtype;
        if !matches!((kind, size), (b'b', 1) | (b'i' | b'u', 1 | 2 | 4 | 8) | (b'f', 4 | 8)) {
            return Err(self.dtype_err(path, array, EXPECTED));
        }
        // Widen every element to (is 0, is 1, text) without allocating per element.
        let flag = |c: &[u8]| -> Option<bool> {
            let mut b = [0u8; 8];
            if big_endian {
                b[8 - size..].copy_from_slice(c);
                b.reverse();
            } else {
                b[..size].copy_from_slice(c);
            }
            let bits = u64::from_le_bytes(b);
            match kind {
                b'f' => {
                    let v = if size == 4 {
                        f32::from_bits(bits as u32) as f64
                    } else {
                        f64::from_bits(bits)
                    };
                    if v == 0.0 {
                        Some(false)
                    } else if v == 1.0 {
                        Some(true)
                    } else {
                        None
                    }
                }
                // Integers and bools: exactly 0 or 1 (a negative signed value has high bits set).
                _ => match bits {
                    0 => Some(false),
                    1 => Some(true),
                    _ => None,
                },
            }
        };
        let mut values = Vec::with_capacity(self.data.len() / size);
        for c in self.data.chunks_exact(size) {
            match flag(c) {
                Some(v) => values.push(v),
                None => {
                    // Position in C order, for the message.
                    let file_pos = values.len();
                    let c_pos = if self.fortran_order {
                        self.fortran_to_c_index(file_pos)
                    } else {
                        file_pos
                    };
                    return Ok(Err((c_pos, self.element_text(c))));
                }
            }
        }
        Ok(Ok(self.to_c_order(values)))
    }

    fn element_text(&self, c: &[u8]) -> String {
        let NpyDtype { kind, size, big_endian } = self.dtype;
        let mut b = [0u8; 8];
        if big_endian {
            b[8 - size..].copy_from_slice(c);
            b.reverse();
        } else {
            b[..size].copy_from_slice(c);
        }
        let bits = u64::from_le_bytes(b);
        match (kind, size) {
            (b'f', 4) => f32::from_bits(bits as u32).to_string(),
            (b'f', _) => f64::from_bits(bits).to_string(),
            (b'i', _) => {
                let shift = 64 - 8 * size as u32;
                (((bits << shift) as i64) >> shift).to_string()
            }
            _ => bits.to_string(),
        }
    }

    /// Reorders file-order values into C order (a no-op for C-order files).
    fn to_c_order<T: Copy + Default>(&self, values: Vec<T>) -> Vec<T> {
        if !self.fortran_order || self.shape.len() < 2 {
            return values;
        }
        let mut out = vec![T::default(); values.len()];
        for (c_pos, v) in out.iter_mut().enumerate() {
            *v = values[self.c_to_fortran_index(c_pos)];
        }
        out
    }

    fn c_to_fortran_index(&self, mut c_pos: usize) -> usize {
        // Peel C-order digits from the last axis; Fortran strides grow from the first axis.
        let mut f_strides = vec![1usize; self.shape.len()];
        for a in 1..self.shape.len() {
            f_strides[a] = f_strides[a - 1] * self.shape[a - 1];
        }
        let mut f_pos = 0;
        for a in (0..self.shape.len()).rev() {
            let i = c_pos % self.shape[a];
            c_pos /= self.shape[a];
            f_pos += i * f_strides[a];
        }
        f_pos
    }

    fn fortran_to_c_index(&self, mut f_pos: usize) -> usize {
        let mut c_strides = vec![1usize; self.shape.len()];
        for a in (0..self.shape.len().saturating_sub(1)).rev() {
            c_strides[a] = c_strides[a + 1] * self.shape[a + 1];
        }
        let mut c_pos = 0;
        for a in 0..self.shape.len() {
            let i = f_pos % self.shape[a];
            f_pos /= self.shape[a];
            c_pos += i * c_strides[a];
        }
        c_pos
    }
}

impl NpyDtype {
    /// Parses a simple descr such as `<f4`, `>f8`, `|b1`, `<i8`; `None` for anything else.
    fn parse(descr: &str) -> Option<Self> {
        let b = descr.as_bytes();
        if b.len() < 3 {
            return None;
        }
        let big_endian = match b[0] {
            b'<' => false,
            b'>' => true,
            b'|' => false,
            b'=' => cfg!(target_endian = "big"),
            _ => return None,
        };
        let kind = b[1];
        if !matches!(kind, b'f' | b'i' | b'u' | b'b') {
            return None;
        }
        let size: usize = descr[2..].parse().ok()?;
        if !(1..=8).contains(&size) {
            return None;
        }
        Some(Self { kind, size, big_endian })
    }
}

/// Encodes a row-major `f32` array of `shape` as `.npy` bytes (little-endian, C order).
pub(crate) fn encode_f32(shape: &[usize], values: &[f32]) -> std::io::Result<Vec<u8>> {
    use npyz::WriterBuilder;
    let shape: Vec<u64> = shape.iter().map(|&s| s as u64).collect();
    let mut bytes = Vec::with_capacity(128 + 4 * values.len());
    let mut writer = npyz::WriteOptions::<f32>::new()
        .default_dtype()
        .shape(&shape)
        .writer(&mut bytes)
        .begin_nd()?;
    writer.extend(values.iter().copied())?;
    writer.finish()?;
    Ok(bytes)
}

/// The subset of Python literals `.npy` headers use.
#[derive(Debug, Clone, PartialEq)]
enum PyValue {
    Str(String),
    Int(u64),
    Bool(bool),
    None,
    Tuple(Vec<PyValue>),
    List(Vec<PyValue>),
    Dict(Vec<(PyValue, PyValue)>),
}

impl PyValue {
    fn parse(text: &str) -> std::result::Result<Self, String> {
        let mut p = PyParser { s: text.as_bytes(), pos: 0 };
        let v = p.value(0)?;
        p.skip_ws();
        if p.pos != p.s.len() {
            return Err(format!("unexpected text at byte {}", p.pos));
        }
        Ok(v)
    }
}

struct PyParser<'a> {
    s: &'a [u8],
    pos: usize,
}

impl PyParser<'_> {
    const MAX_DEPTH: usize = 8;

    fn skip_ws(&mut self) {
        while self.pos < self.s.len() && self.s[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.pos).copied()
    }

    fn value(&mut self, depth: usize) -> std::result::Result<PyValue, String> {
        if depth > Self::MAX_DEPTH {
            return Err("nested too deeply".into());
        }
        match self.peek().ok_or("unexpected end")? {
            b'{' => {
                self.pos += 1;
                let mut items = Vec::new();
                loop {
                    if self.peek() == Some(b'}') {
                        self.pos += 1;
                        return Ok(PyValue::Dict(items));
                    }
                    let k = self.value(depth + 1)?;
                    if self.peek() != Some(b':') {
                        return Err(format!("expected ':' at byte {}", self.pos));
                    }
                    self.pos += 1;
                    let v = self.value(depth + 1)?;
                    items.push((k, v));
                    match self.peek() {
                        Some(b',') => self.pos += 1,
                        Some(b'}') => {}
                        _ => return Err(format!("expected ',' or '}}' at byte {}", self.pos)),
                    }
                }
            }
            open @ (b'(' | b'[') => {
                let close = if open == b'(' { b')' } else { b']' };
                self.pos += 1;
                let mut items = Vec::new();
                loop {
                    if self.peek() == Some(close) {
                        self.pos += 1;
                        return Ok(if open == b'(' {
                            PyValue::Tuple(items)
                        } else {
                            PyValue::List(items)
                        });
                    }
                    items.push(self.value(depth + 1)?);
                    match self.peek() {
                        Some(b',') => self.pos += 1,
                        Some(c) if c == close => {}
                        _ => {
                            return Err(format!(
                                "expected ',' or closing bracket at byte {}",
                                self.pos
                            ));
                        }
                    }
                }
            }
            q @ (b'\'' | b'"') => {
                self.pos += 1;
                let mut out = Vec::new();
                loop {
                    let c = *self.s.get(self.pos).ok_or("unterminated string")?;
                    self.pos += 1;
                    if c == q {
                        break;
                    }
                    if c == b'\\' {
                        out.push(*self.s.get(self.pos).ok_or("unterminated string")?);
                        self.pos += 1;
                    } else {
                        out.push(c);
                    }
                }
                String::from_utf8(out)
                    .map(PyValue::Str)
                    .map_err(|_| "string is not valid text".into())
            }
            c if c.is_ascii_digit() => {
                let mut n: u64 = 0;
                while let Some(&d) = self.s.get(self.pos).filter(|d| d.is_ascii_digit()) {
                    n = n
                        .checked_mul(10)
                        .and_then(|n| n.checked_add(u64::from(d - b'0')))
                        .ok_or("integer too large")?;
                    self.pos += 1;
                }
                // Python 2 long suffix, as old numpy wrote it.
                if self.s.get(self.pos) == Some(&b'L') {
                    self.pos += 1;
                }
                Ok(PyValue::Int(n))
            }
            _ => {
                for (word, v) in [
                    ("True", PyValue::Bool(true)),
                    ("False", PyValue::Bool(false)),
                    ("None", PyValue::None),
                ] {
                    if self.s[self.pos..].starts_with(word.as_bytes()) {
                        self.pos += word.len();
                        return Ok(v);
                    }
                }
                Err(format!("unexpected character at byte {}", self.pos))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(header: &str, data: &[u8]) -> Vec<u8> {
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn path() -> &'static Path {
        Path::new("test.npy")
    }

    #[test]
    fn parses_python_literals() {
        let v =
            PyValue::parse("{'descr': '<f4', \"fortran_order\": False, 'shape': (3, 4L,), }  \n")
                .unwrap();
        assert_eq!(
            v,
            PyValue::Dict(vec![
                (PyValue::Str("descr".into()), PyValue::Str("<f4".into())),
                (PyValue::Str("fortran_order".into()), PyValue::Bool(false)),
                (
                    PyValue::Str("shape".into()),
                    PyValue::Tuple(vec![PyValue::Int(3), PyValue::Int(4)])
                ),
            ])
        );
        assert_eq!(PyValue::parse("()").unwrap(), PyValue::Tuple(vec![]));
        assert_eq!(
            PyValue::parse("[None, True]").unwrap(),
            PyValue::List(vec![PyValue::None, PyValue::Bool(true)])
        );
        for bad in [
            "{",
            "{'a' 1}",
            "(1 2)",
            "'abc",
            "99999999999999999999999",
            "x",
            "((((((((((1))))))))))",
            "1 2",
        ] {
            assert!(PyValue::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn round_trips_through_the_npyz_writer() {
        let values: Vec<f32> = (0..24).map(|i| i as f32 * 0.37 - 3.0).collect();
        let bytes = encode_f32(&[2, 3, 4], &values).unwrap();
        let a = NpyArray::parse(&bytes, path(), "x").unwrap();
        assert_eq!(a.shape, vec![2, 3, 4]);
        assert_eq!(a.to_f32(path(), "x").unwrap(), values);
        // And npyz's own reader agrees with the bytes.
        let back: Vec<f32> = npyz::NpyFile::new(&bytes[..]).unwrap().into_vec().unwrap();
        assert_eq!(back, values);
    }

    #[test]
    fn reads_fortran_order_and_big_endian() {
        // 2 x 3 array [[0, 1, 2], [3, 4, 5]] stored in Fortran order as big-endian f8.
        let f_order = [0.0f64, 3.0, 1.0, 4.0, 2.0, 5.0];
        let data: Vec<u8> = f_order.iter().flat_map(|v| v.to_be_bytes()).collect();
        let bytes = npy("{'descr': '>f8', 'fortran_order': True, 'shape': (2, 3), }", &data);
        let a = NpyArray::parse(&bytes, path(), "x").unwrap();
        assert_eq!(a.to_f32(path(), "x").unwrap(), vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        // A mask in Fortran order with a bad value reports its C-order position.
        let m =
            npy("{'descr': '|u1', 'fortran_order': True, 'shape': (2, 3), }", &[1, 1, 1, 7, 0, 0]);
        let a = NpyArray::parse(&m, path(), "m").unwrap();
        // File position 3 is (row 1, col 1) -> C index 4.
        assert_eq!(a.to_mask(path(), "m").unwrap(), Err((4, "7".to_string())));
    }

    #[test]
    fn masks_accept_0_1_in_any_numeric_dtype() {
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("|b1", vec![1, 0]),
            ("<i8", [1i64, 0].iter().flat_map(|v| v.to_le_bytes()).collect()),
            (">i2", [1i16, 0].iter().flat_map(|v| v.to_be_bytes()).collect()),
            ("<f4", [1.0f32, 0.0].iter().flat_map(|v| v.to_le_bytes()).collect()),
            ("<f8", [1.0f64, -0.0].iter().flat_map(|v| v.to_le_bytes()).collect()),
        ];
        for (descr, data) in cases {
            let bytes = npy(
                &format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': (2,), }}"),
                &data,
            );
            let a = NpyArray::parse(&bytes, path(), "m").unwrap();
            assert_eq!(a.to_mask(path(), "m").unwrap(), Ok(vec![true, false]), "{descr}");
        }
        let neg: Vec<u8> = [1i32, -1].iter().flat_map(|v| v.to_le_bytes()).collect();
        let bytes = npy("{'descr': '<i4', 'fortran_order': False, 'shape': (2,), }", &neg);
        let a = NpyArray::parse(&bytes, path(), "m").unwrap();
        assert_eq!(a.to_mask(path(), "m").unwrap(), Err((1, "-1".to_string())));
        let half: Vec<u8> = 0.5f32.to_le_bytes().to_vec();
        let bytes = npy("{'descr': '<f4', 'fortran_order': False, 'shape': (1,), }", &half);
        let a = NpyArray::parse(&bytes, path(), "m").unwrap();
        assert_eq!(a.to_mask(path(), "m").unwrap(), Err((0, "0.5".to_string())));
    }

    #[test]
    fn rejects_malformed_files() {
        let f4 = |n: usize| vec![0u8; 4 * n];
        let err = |bytes: Vec<u8>| NpyArray::parse(&bytes, path(), "x").unwrap_err();
        assert!(matches!(err(b"PK\x03\x04 not npy".to_vec()), DataError::Format { .. }));
        assert!(matches!(err(b"\x93NUMPY\x01\x00\xff\x00{".to_vec()), DataError::Format { .. }));
        let h = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }";
        assert!(matches!(err(npy(h, &f4(5))), DataError::Format { .. })); // truncated
        assert!(matches!(err(npy(h, &f4(7))), DataError::Format { .. })); // trailing bytes
        let huge = "{'descr': '<f4', 'fortran_order': False, 'shape': (4294967296, 4294967296, 4294967296), }";
        assert!(matches!(err(npy(huge, &f4(1))), DataError::Format { .. }));
        let no_shape = "{'descr': '<f4', 'fortran_order': False}";
        assert!(matches!(err(npy(no_shape, &f4(1))), DataError::Format { .. }));
        let structured = "{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (1,), }";
        assert!(matches!(err(npy(structured, &f4(1))), DataError::Dtype { .. }));
        let mut v3 = npy(h, &f4(6));
        v3[6] = 9;
        assert!(matches!(err(v3), DataError::Format { .. }));
        // Dtypes that parse but do not fit the role are rejected by the decoders.
        let ints = npy("{'descr': '<i4', 'fortran_order': False, 'shape': (1,), }", &f4(1));
        let a = NpyArray::parse(&ints, path(), "x").unwrap();
        assert!(matches!(a.to_f32(path(), "x"), Err(DataError::Dtype { .. })));
        let half = npy("{'descr': '<f2', 'fortran_order': False, 'shape': (2,), }", &f4(1));
        let a = NpyArray::parse(&half, path(), "x").unwrap();
        assert!(matches!(a.to_f32(path(), "x"), Err(DataError::Dtype { .. })));
        let obj = npy("{'descr': '|O', 'fortran_order': False, 'shape': (1,), }", &[0; 8]);
        let a = NpyArray::parse(&obj, path(), "x").unwrap();
        assert!(matches!(a.to_mask(path(), "x"), Err(DataError::Dtype { .. })));
    }
}
