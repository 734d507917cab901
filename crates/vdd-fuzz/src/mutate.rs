//! The mutation engine: seeded byte-level mutations of any file, and
//! structure-aware ones for the formats the loaders read (an `.npy` header, a `safetensors`
//! header and its JSON metadata, JSON and TOML documents), which keep the container valid so
//! that the mutated values reach the checks behind it.

use rand::Rng as _;
use rand::seq::IndexedRandom as _;
use rand_chacha::ChaCha8Rng as Rng;
use serde_json::Value;

/// Interesting numbers as text: limits, overflows, non-finite spellings.
const NUMBERS: &[&str] = &[
    "0",
    "-1",
    "1",
    "2",
    "-0",
    "3",
    "7",
    "16",
    "255",
    "65536",
    "1000000",
    "2147483648",
    "4294967296",
    "4611686018427387905",
    "9223372036854775807",
    "18446744073709551615",
    "1e39",
    "-1e39",
    "3.4e38",
    "-3.4e38",
    "1e-45",
    "1e300",
    "NaN",
    "inf",
    "-inf",
    "1e6",
    "0.5",
];

/// Interesting JSON values for a leaf of a document.
fn json_value(rng: &mut Rng) -> Value {
    let n: &str = NUMBERS.choose(rng).copied().unwrap_or("0");
    match rng.random_range(0..10) {
        0 => Value::String(n.to_owned()),
        1 => Value::Null,
        2 => Value::Bool(rng.random()),
        3 => Value::Array(Vec::new()),
        _ => serde_json::from_str(n).unwrap_or_else(|_| Value::String(n.to_owned())),
    }
}

/// Interesting little-endian byte patterns: f32/f64 extremes, integer limits.
fn pattern(rng: &mut Rng) -> Vec<u8> {
    match rng.random_range(0..9) {
        0 => f32::NAN.to_le_bytes().to_vec(),
        1 => f32::INFINITY.to_le_bytes().to_vec(),
        2 => f32::MAX.to_le_bytes().to_vec(),
        3 => (-3.0e38f32).to_le_bytes().to_vec(),
        4 => 1.0e7f32.to_le_bytes().to_vec(),
        5 => 1.0e39f64.to_le_bytes().to_vec(),
        6 => u32::MAX.to_le_bytes().to_vec(),
        7 => u64::MAX.to_le_bytes().to_vec(),
        _ => vec![0; rng.random_range(1..16)],
    }
}

/// One to four byte-level mutations: bit flips, interesting bytes and patterns, truncation,
/// extension, a copied region.
pub fn bytes(rng: &mut Rng, data: &mut Vec<u8>) {
    for _ in 0..rng.random_range(1..=4) {
        let len = data.len();
        let at = if len == 0 { 0 } else { rng.random_range(0..len) };
        match rng.random_range(0..8) {
            0 | 1 if len > 0 => data[at] ^= 1 << rng.random_range(0..8),
            2 if len > 0 => data[at] = *[0u8, 1, 0x7f, 0x80, 0xff].choose(rng).unwrap_or(&0),
            3 | 4 => {
                for (k, b) in pattern(rng).into_iter().enumerate() {
                    if let Some(x) = data.get_mut(at + k) {
                        *x = b;
                    }
                }
            }
            5 => data.truncate(at),
            6 => {
                let extra = rng.random_range(1..64);
                data.extend((0..extra).map(|_| if rng.random() { 0 } else { rng.random::<u8>() }));
            }
            _ if len > 1 => {
                let from = rng.random_range(0..len);
                let n = rng.random_range(1..=(len - from).min(32));
                let chunk = data[from..from + n].to_vec();
                let to = rng.random_range(0..len);
                data.splice(to..(to + n).min(len), chunk);
            }
            _ => data.push(0),
        }
    }
}

/// Replaces a random run of digits (a number, a shape entry) in `text` by an interesting number.
pub fn text_number(rng: &mut Rng, text: &str) -> String {
    let runs: Vec<(usize, usize)> = {
        let b = text.as_bytes();
        let mut v = Vec::new();
        let mut i = 0;
        while i < b.len() {
            if b[i].is_ascii_digit() {
                let s = i;
                while i < b.len() && (b[i].is_ascii_digit() || b[i] == b'.' || b[i] == b'e') {
                    i += 1;
                }
                v.push((s, i));
            } else {
                i += 1;
            }
        }
        v
    };
    match runs.choose(rng) {
        Some(&(s, e)) => {
            let n = NUMBERS.choose(rng).copied().unwrap_or("0");
            format!("{}{n}{}", &text[..s], &text[e..])
        }
        None => text.to_owned(),
    }
}

/// Mutates a JSON document: a random leaf replaced by an interesting value, an array shortened
/// or lengthened, or a key dropped. Nested JSON held in strings (`safetensors` metadata) is
/// mutated too.
pub fn json(rng: &mut Rng, v: &mut Value) {
    let mut paths = Vec::new();
    collect(v, &mut Vec::new(), &mut paths);
    let Some(path) = paths.choose(rng).cloned() else { return };
    let Some(target) = pointer(v, &path) else { return };
    match target {
        Value::String(s) if rng.random_bool(0.7) => {
            if let Ok(mut inner) = serde_json::from_str::<Value>(s) {
                if inner.is_object() || inner.is_array() {
                    json(rng, &mut inner);
                    *s = inner.to_string();
                    return;
                }
            }
            *target = json_value(rng);
        }
        Value::Array(a) if !a.is_empty() && rng.random_bool(0.5) => {
            if rng.random() {
                a.truncate(rng.random_range(0..a.len()));
            } else {
                let x = a[0].clone();
                a.extend(std::iter::repeat_n(x, rng.random_range(1..4)));
            }
        }
        Value::Object(m) if !m.is_empty() && rng.random_bool(0.3) => {
            let keys: Vec<String> = m.keys().cloned().collect();
            if let Some(k) = keys.choose(rng) {
                m.remove(k);
            }
        }
        _ => *target = json_value(rng),
    }
}

fn collect(v: &Value, at: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
    out.push(at.clone());
    let children: Vec<(String, &Value)> = match v {
        Value::Object(m) => m.iter().map(|(k, x)| (k.clone(), x)).collect(),
        Value::Array(a) => a.iter().enumerate().map(|(i, x)| (i.to_string(), x)).collect(),
        _ => Vec::new(),
    };
    for (k, x) in children {
        at.push(k);
        collect(x, at, out);
        at.pop();
    }
}

fn pointer<'a>(v: &'a mut Value, path: &[String]) -> Option<&'a mut Value> {
    path.iter().try_fold(v, |v, k| match v {
        Value::Object(m) => m.get_mut(k),
        Value::Array(a) => a.get_mut(k.parse::<usize>().ok()?),
        _ => None,
    })
}

/// Mutates an `.npy` file: its header text (shape, dtype, order; the header length is
/// rewritten), its data (interesting floats), or its bytes.
pub fn npy(rng: &mut Rng, data: &mut Vec<u8>) {
    let header = (data.len() >= 10 && data.starts_with(b"\x93NUMPY") && data[6] == 1)
        .then(|| 10 + u16::from_le_bytes([data[8], data[9]]) as usize)
        .filter(|&end| end <= data.len());
    match (header, rng.random_range(0..4)) {
        (Some(end), 0 | 1) => {
            let text = String::from_utf8_lossy(&data[10..end]).into_owned();
            let text = if rng.random_bool(0.7) {
                text_number(rng, &text)
            } else {
                let d = ["'<f8'", "'>f4'", "'|b1'", "'<i8'", "'<c8'", "'O'", "'<f2'", "'<u1'"];
                let t = text.replacen("'<f4'", d.choose(rng).unwrap_or(&"''"), 1);
                t.replacen("False", if rng.random() { "True" } else { "1" }, 1)
            };
            let mut out = data[..8].to_vec();
            out.extend((text.len() as u16).to_le_bytes());
            out.extend(text.as_bytes());
            out.extend(&data[end..]);
            // Often the data are resized to what the new header declares (when small), so the
            // edit reaches the checks behind the size check.
            if let Some(n) = declared_bytes(&text).filter(|&n| n <= 1 << 20 && rng.random()) {
                out.resize(10 + text.len() + n, 0);
            }
            *data = out;
        }
        (Some(end), 2) if end + 4 <= data.len() => {
            let at = end + 4 * rng.random_range(0..(data.len() - end) / 4);
            for (k, b) in pattern(rng).into_iter().take(4).enumerate() {
                if let Some(x) = data.get_mut(at + k) {
                    *x = b;
                }
            }
        }
        _ => bytes(rng, data),
    }
}

/// The data bytes an `.npy` header text declares (`<f4`/`<f8`/`|b1` and a shape), if it parses.
fn declared_bytes(header: &str) -> Option<usize> {
    let size: usize = [("f4'", 4), ("f8'", 8), ("b1'", 1), ("i8'", 8), ("u1'", 1)]
        .iter()
        .find(|(d, _)| header.contains(d))?
        .1;
    let shape = header.split("'shape':").nth(1)?.split(')').next()?.trim().trim_start_matches('(');
    shape
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .try_fold(size, |acc, d| acc.checked_mul(d.parse::<usize>().ok()?))
}

/// Mutates a `safetensors` file: its JSON header (tensor shapes, offsets and dtypes, the
/// metadata and the JSON inside it; the header length is rewritten), a weight (interesting
/// floats), or its bytes.
pub fn safetensors(rng: &mut Rng, data: &mut Vec<u8>) {
    let n = data.get(..8).map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])) as usize);
    let end = n.and_then(|n| n.checked_add(8)).filter(|&e| e <= data.len());
    let parsed = end.and_then(|e| serde_json::from_slice::<Value>(&data[8..e]).ok());
    match (end, parsed, rng.random_range(0..5)) {
        (Some(end), Some(mut header), 0..=2) => {
            // Half the time a field of one metadata entry (a config, normalisers, a spec),
            // keeping it a string holding JSON; otherwise anything in the header.
            let meta = header.get_mut("__metadata__").and_then(Value::as_object_mut);
            let entry = meta.and_then(|m| {
                let keys: Vec<String> = m.keys().cloned().collect();
                let k = keys.choose(rng)?.clone();
                m.get_mut(&k)
            });
            match entry {
                Some(Value::String(text)) if rng.random() => {
                    if let Ok(mut inner) = serde_json::from_str::<Value>(text) {
                        json(rng, &mut inner);
                        *text = inner.to_string();
                    } else {
                        *text = text_number(rng, text);
                    }
                }
                _ => json(rng, &mut header),
            }
            let text = header.to_string();
            let mut out = (text.len() as u64).to_le_bytes().to_vec();
            out.extend(text.as_bytes());
            out.extend(&data[end..]);
            *data = out;
        }
        (Some(end), _, 3) if end + 4 <= data.len() => {
            let at = end + 4 * rng.random_range(0..(data.len() - end) / 4);
            for (k, b) in pattern(rng).into_iter().take(4).enumerate() {
                if let Some(x) = data.get_mut(at + k) {
                    *x = b;
                }
            }
        }
        _ => bytes(rng, data),
    }
}

/// Mutates a JSON file (structure-aware most of the time).
pub fn json_file(rng: &mut Rng, data: &mut Vec<u8>) {
    match serde_json::from_slice::<Value>(data) {
        Ok(mut v) if rng.random_bool(0.8) => {
            json(rng, &mut v);
            *data = v.to_string().into_bytes();
        }
        _ => bytes(rng, data),
    }
}

/// Mutates a TOML file: a key set to an interesting value (as a dotted `key = value` line
/// appended, which the recipe format merges), a number in the text replaced, or its bytes.
pub fn toml_file(rng: &mut Rng, data: &mut Vec<u8>, keys: &[&str]) {
    let text = String::from_utf8_lossy(data).into_owned();
    let out = match rng.random_range(0..4) {
        0 | 1 => {
            let key = keys.choose(rng).copied().unwrap_or("seeds");
            let n = NUMBERS.choose(rng).copied().unwrap_or("0");
            let value = match n {
                "NaN" => "nan",
                "1e39" | "-1e39" | "1e300" | "inf" | "-inf" | "3.4e38" | "-3.4e38" | "1e-45"
                | "1e6" | "0.5" => n,
                _ if rng.random() => n,
                _ => "\"x\"",
            };
            // A quoted dotted key expands like `--set`; top-level keys precede the tables.
            format!("\"{key}\" = {value}\n{text}")
        }
        2 => text_number(rng, &text),
        _ => {
            let mut b = text.into_bytes();
            bytes(rng, &mut b);
            *data = b;
            return;
        }
    };
    *data = out.into_bytes();
}

/// Interesting YAML values for a `key: value` line: numbers, YAML's own spellings of null,
/// booleans and non-finite floats, empty and flow collections, OmegaConf interpolations
/// (missing, cyclic, to a mapping), aliases and tags.
const YAML_VALUES: &[&str] = &[
    "null",
    "~",
    "''",
    "[]",
    "{}",
    "true",
    "no",
    ".inf",
    "-.inf",
    ".nan",
    "0x10",
    "1_000",
    "-5",
    "[1, 2]",
    "{a: 1}",
    "${obs_dim}",
    "${agents}",
    "${missing.key}",
    "${agents.model.inner_model._target_}",
    "\"${window_size}\"",
    "${agents.window_size}",
    "*undefined",
    "&anchor 3",
    "!!binary AAAA",
    "!!float 1e39",
    "|\n  block",
];

/// Mutates a YAML file as text: the value of a `key: value` line replaced by an interesting
/// one, a number replaced, a line dropped or repeated, a billion-laughs alias bomb prepended,
/// or its bytes.
pub fn yaml_file(rng: &mut Rng, data: &mut Vec<u8>) {
    let text = String::from_utf8_lossy(data).into_owned();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let valued: Vec<usize> = (0..lines.len()).filter(|&i| key_value(&lines[i]).is_some()).collect();
    match rng.random_range(0..10) {
        0..=3 if !valued.is_empty() => {
            let i = valued[rng.random_range(0..valued.len())];
            let at = key_value(&lines[i]).unwrap_or(lines[i].len());
            let value = if rng.random_bool(0.4) {
                NUMBERS.choose(rng).copied().unwrap_or("0")
            } else {
                YAML_VALUES.choose(rng).copied().unwrap_or("null")
            };
            lines[i] = format!("{}{value}", &lines[i][..at]);
        }
        4 | 5 => {
            *data = text_number(rng, &text).into_bytes();
            return;
        }
        6 if !lines.is_empty() => {
            lines.remove(rng.random_range(0..lines.len()));
        }
        7 if !lines.is_empty() => {
            let i = rng.random_range(0..lines.len());
            let line = lines[i].clone();
            lines.insert(i, line);
        }
        8 => {
            // Nine levels of nine aliases each: 9^9 nodes if expanded.
            let mut bomb = vec!["l0: &l0 [x, x, x, x, x, x, x, x, x]".to_owned()];
            for k in 1..9 {
                let refs = vec![format!("*l{}", k - 1); 9].join(", ");
                bomb.push(format!("l{k}: &l{k} [{refs}]"));
            }
            lines.splice(0..0, bomb);
        }
        _ => {
            bytes(rng, data);
            return;
        }
    }
    *data = (lines.join("\n") + "\n").into_bytes();
}

/// Where the value of a `key: value` line starts (after `": "`), if the line has one.
fn key_value(line: &str) -> Option<usize> {
    let t = line.trim_start();
    let colon = t.find(": ")?;
    let key = &t[..colon];
    let plain = !key.is_empty() && key.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_');
    (plain && !t[colon + 2..].trim().is_empty()).then(|| line.len() - t.len() + colon + 2)
}

/// Text nested deeply: `[`/`{` (or YAML's compact `- ` sequences) 65, 1,000 or 100,000 levels
/// deep, closed or left open, in JSON's spelling or YAML's flow or block style.
pub fn deep_text(rng: &mut Rng, yaml: bool) -> String {
    let depth = [65usize, 1000, 100_000].choose(rng).copied().unwrap_or(100_000);
    let closed = rng.random_bool(0.7);
    let (open, close) = match rng.random_range(0..4) {
        0 => ("[", "]"),
        1 => ("[1, ", "]"),
        2 if yaml => ("{a: ", "}"),
        2 => ("{\"a\": ", "}"),
        _ if yaml => return format!("{}x", "- ".repeat(depth)),
        _ => ("[[], ", "]"),
    };
    let mut s = open.repeat(depth);
    s.push('1');
    if closed {
        s.push_str(&close.repeat(depth));
    }
    s
}

/// Marks where [`json_deep`] splices the deep text into a serialised document.
const DEEP_MARK: &str = "@@vdd-fuzz-deep@@";

/// A JSON file with a random value (or the whole document) replaced by [`deep_text`].
pub fn json_deep(rng: &mut Rng, data: &mut Vec<u8>) {
    let deep = deep_text(rng, false);
    let Ok(mut v) = serde_json::from_slice::<Value>(data) else {
        *data = deep.into_bytes();
        return;
    };
    let mut paths = Vec::new();
    collect(&v, &mut Vec::new(), &mut paths);
    let path = paths.choose(rng).cloned().unwrap_or_default();
    if let Some(target) = pointer(&mut v, &path) {
        *target = Value::String(DEEP_MARK.to_owned());
    }
    let text = v.to_string().replacen(&format!("\"{DEEP_MARK}\""), &deep, 1);
    *data = text.into_bytes();
}

/// A YAML file with the value of a `key: value` line replaced by deep flow text, a deep key
/// added at the top, or the whole document replaced ([`deep_text`]).
pub fn yaml_deep(rng: &mut Rng, data: &mut Vec<u8>) {
    let deep = deep_text(rng, true);
    let text = String::from_utf8_lossy(data).into_owned();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let valued: Vec<usize> = (0..lines.len()).filter(|&i| key_value(&lines[i]).is_some()).collect();
    match rng.random_range(0..3) {
        0 if !valued.is_empty() && !deep.starts_with('-') => {
            let i = valued[rng.random_range(0..valued.len())];
            let at = key_value(&lines[i]).unwrap_or(lines[i].len());
            lines[i] = format!("{}{deep}", &lines[i][..at]);
        }
        0 | 1 => lines.insert(0, format!("deep:\n  {deep}")),
        _ => lines = vec![deep],
    }
    *data = (lines.join("\n") + "\n").into_bytes();
}
