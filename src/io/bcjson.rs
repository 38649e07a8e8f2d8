//! Constraint input: the per-node JSON of docs/formats.md, "Constraint JSON" (`bc.json`), and
//! the global form B Δx = p (B.mtx with optional p.mtx) where every row of B touches one
//! node.
//!
//! The JSON is read into a `serde_json::Value` and walked by hand (not derived) so that
//! every fault names its JSON path, e.g. `constraints[3].normal[1]`.

use super::mtx;
use crate::core::constraints::{node_rows, Constraint, ConstraintKind};
use crate::error::InputError;
use serde_json::{Map, Value};
use std::fmt::Write as _;

/// The contents of bc.json.
#[derive(Debug, Clone, PartialEq)]
pub struct ConstraintFile {
    /// `dim` when the file states it.
    pub dim: Option<usize>,
    pub constraints: Vec<Constraint>,
}

fn err(file: &str, entry: impl Into<String>, problem: impl Into<String>) -> InputError {
    InputError::new(file, entry, problem)
}

/// Marks numbers that overflow f64 (serde_json rejects them as a parse error without a
/// path): they are rewritten as strings and reported by path as not finite.
const OVERFLOW_TAG: &str = "\u{1}overflow:";

/// Rewrites number tokens outside strings whose value is not a finite f64 (e.g. 1e999)
/// as tagged strings. Returns None when there are none (the common case: no copy).
fn tag_overflowing_numbers(text: &str) -> Option<String> {
    let b = text.as_bytes();
    let mut out: Option<String> = None;
    let mut last = 0;
    let mut i = 0;
    let mut in_str = false;
    while i < b.len() {
        let ch = b[i];
        if in_str {
            if ch == b'\\' {
                i += 2;
                continue;
            }
            if ch == b'"' {
                in_str = false;
            }
            i += 1;
            continue;
        }
        if ch == b'"' {
            in_str = true;
            i += 1;
            continue;
        }
        if ch == b'-' || ch.is_ascii_digit() {
            let s = i;
            while i < b.len() && matches!(b[i], b'0'..=b'9' | b'-' | b'+' | b'.' | b'e' | b'E') {
                i += 1;
            }
            let tok = &text[s..i];
            if let Ok(v) = tok.parse::<f64>() {
                if !v.is_finite() {
                    let o = out.get_or_insert_with(|| String::with_capacity(text.len() + 16));
                    o.push_str(&text[last..s]);
                    // The tag's control character must be escaped inside JSON.
                    o.push_str("\"\\u0001overflow:");
                    o.push_str(tok);
                    o.push('"');
                    last = i;
                }
            }
            continue;
        }
        i += 1;
    }
    out.map(|mut o| {
        o.push_str(&text[last..]);
        o
    })
}

/// Marks the error of a repeated key; the rest of the message is the key's JSON path.
const DUPLICATE_TAG: &str = "\u{1}duplicate:";

/// One step of the JSON path of the value being read (built only when an error needs it).
enum Step<'a> {
    Key(&'a str),
    Index(usize),
}

struct At<'a> {
    parent: Option<&'a At<'a>>,
    step: Step<'a>,
}

fn path_of(at: Option<&At>, key: &str) -> String {
    let mut steps = Vec::new();
    let mut cur = at;
    while let Some(a) = cur {
        steps.push(a);
        cur = a.parent;
    }
    let mut s = String::new();
    for a in steps.iter().rev() {
        match a.step {
            Step::Key(k) => {
                if !s.is_empty() {
                    s.push('.');
                }
                s.push_str(k);
            }
            Step::Index(i) => {
                let _ = write!(s, "[{i}]");
            }
        }
    }
    if !s.is_empty() {
        s.push('.');
    }
    s.push_str(key);
    s
}

/// Deserializes a `serde_json::Value` as serde_json does, except that an object that
/// repeats a key is an error (serde_json keeps the last value silently).
struct UniqueKeys<'a> {
    at: Option<&'a At<'a>>,
}

impl<'de> serde::de::DeserializeSeed<'de> for UniqueKeys<'_> {
    type Value = Value;
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<Value, D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> serde::de::Visitor<'de> for UniqueKeys<'_> {
    type Value = Value;
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("any JSON value")
    }
    fn visit_bool<E>(self, v: bool) -> Result<Value, E> {
        Ok(Value::Bool(v))
    }
    fn visit_i64<E>(self, v: i64) -> Result<Value, E> {
        Ok(Value::Number(v.into()))
    }
    fn visit_u64<E>(self, v: u64) -> Result<Value, E> {
        Ok(Value::Number(v.into()))
    }
    fn visit_f64<E>(self, v: f64) -> Result<Value, E> {
        Ok(serde_json::Number::from_f64(v).map_or(Value::Null, Value::Number))
    }
    fn visit_str<E>(self, v: &str) -> Result<Value, E> {
        Ok(Value::String(v.to_string()))
    }
    fn visit_string<E>(self, v: String) -> Result<Value, E> {
        Ok(Value::String(v))
    }
    fn visit_unit<E>(self) -> Result<Value, E> {
        Ok(Value::Null)
    }
    fn visit_none<E>(self) -> Result<Value, E> {
        Ok(Value::Null)
    }
    fn visit_some<D: serde::Deserializer<'de>>(self, d: D) -> Result<Value, D::Error> {
        serde::de::DeserializeSeed::deserialize(self, d)
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Value, A::Error> {
        let mut out = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(4096));
        loop {
            let at = At {
                parent: self.at,
                step: Step::Index(out.len()),
            };
            match seq.next_element_seed(UniqueKeys { at: Some(&at) })? {
                Some(v) => out.push(v),
                None => return Ok(Value::Array(out)),
            }
        }
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<Value, A::Error> {
        let mut out = Map::new();
        while let Some(key) = map.next_key::<String>()? {
            if out.contains_key(&key) {
                return Err(serde::de::Error::custom(format!(
                    "{DUPLICATE_TAG}{}",
                    path_of(self.at, &key)
                )));
            }
            let v = {
                let at = At {
                    parent: self.at,
                    step: Step::Key(&key),
                };
                map.next_value_seed(UniqueKeys { at: Some(&at) })?
            };
            out.insert(key, v);
        }
        Ok(Value::Object(out))
    }
}

/// Parses JSON text into a Value, refusing repeated keys.
fn from_str_unique(text: &str) -> Result<Value, serde_json::Error> {
    let mut de = serde_json::Deserializer::from_str(text);
    let v = serde::de::DeserializeSeed::deserialize(UniqueKeys { at: None }, &mut de)?;
    de.end()?;
    Ok(v)
}

fn number(file: &str, path: &str, v: &Value) -> Result<f64, InputError> {
    match v {
        Value::Number(n) => n
            .as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| err(file, path, format!("{n} is not a finite number"))),
        Value::String(s) if s.starts_with(OVERFLOW_TAG) => Err(err(
            file,
            path,
            format!("{} is not a finite number", &s[OVERFLOW_TAG.len()..]),
        )),
        other => Err(err(
            file,
            path,
            format!("expected a number, found {}", kind_of(other)),
        )),
    }
}

/// A value from the file quoted in a message: its JSON, one line, at most 60 characters.
fn shown(v: &Value) -> String {
    super::one_line(&v.to_string(), 60)
}

fn kind_of(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// A vector of `dim` finite numbers (`dim` None: any length ≥ 1).
fn vector(file: &str, path: &str, v: &Value, dim: Option<usize>) -> Result<Vec<f64>, InputError> {
    let Value::Array(a) = v else {
        return Err(err(
            file,
            path,
            format!("expected an array of numbers, found {}", kind_of(v)),
        ));
    };
    if let Some(d) = dim {
        if a.len() != d {
            return Err(err(
                file,
                path,
                format!("has {} components, expected {d} (dim is {d})", a.len()),
            ));
        }
    }
    a.iter()
        .enumerate()
        .map(|(k, x)| number(file, &format!("{path}[{k}]"), x))
        .collect()
}

fn nonzero(file: &str, path: &str, v: &[f64]) -> Result<(), InputError> {
    if v.iter().all(|&x| x == 0.0) {
        return Err(err(
            file,
            path,
            "is zero (a normal or direction needs a nonzero length)",
        ));
    }
    Ok(())
}

const KINDS: &str = "sticky, plane, line or rows";

/// Parses bc.json. `dim`: the dimension from the command line, if given; it must agree
/// with the file's `dim` when both are present. Vectors are checked against the
/// dimension when it is known. Node ranges and rank/consistency are checked later by
/// `Frames::build`, whose errors carry the `constraints[k]` labels.
pub fn parse(file: &str, text: &str, dim: Option<usize>) -> Result<ConstraintFile, InputError> {
    let text = super::strip_bom(text);
    let tagged = tag_overflowing_numbers(text);
    let root: Value = from_str_unique(tagged.as_deref().unwrap_or(text)).map_err(|e| {
        // serde_json appends " at line L column C"; move the position into the entry.
        let msg = e.to_string();
        let msg = msg.rsplit_once(" at line ").map_or(msg.as_str(), |m| m.0);
        let (line, column) = (e.line(), e.column());
        match msg.strip_prefix(DUPLICATE_TAG) {
            Some(path) => err(
                file,
                super::one_line(path, 200),
                format!(
                    "duplicate key (the object gives it again at line {line}, column {column})"
                ),
            ),
            None => err(
                file,
                format!("line {line}, column {column}"),
                format!("malformed JSON: {}", super::one_line(msg, 200)),
            ),
        }
    })?;
    let Value::Object(top) = &root else {
        return Err(err(
            file,
            "",
            format!(
                "expected a JSON object at the top level, found {}",
                kind_of(&root)
            ),
        ));
    };
    for k in top.keys() {
        if k != "dim" && k != "constraints" {
            return Err(err(
                file,
                super::one_line(k, 60),
                "unknown key (expected dim and constraints)",
            ));
        }
    }
    let file_dim = match top.get("dim") {
        None => None,
        Some(v) => match v.as_u64() {
            Some(d @ (2 | 3)) => Some(d as usize),
            _ => {
                return Err(err(
                    file,
                    "dim",
                    format!("must be 2 or 3, found {}", shown(v)),
                ))
            }
        },
    };
    if let (Some(a), Some(b)) = (dim, file_dim) {
        if a != b {
            return Err(err(
                file,
                "dim",
                format!("the file says dim {b} but --dim is {a}"),
            ));
        }
    }
    let dim = dim.or(file_dim);
    let list = match top.get("constraints") {
        Some(Value::Array(a)) => a,
        Some(v) => {
            return Err(err(
                file,
                "constraints",
                format!("expected an array, found {}", kind_of(v)),
            ))
        }
        None => {
            return Err(err(
                file,
                "constraints",
                "missing (use [] for no constraints)",
            ))
        }
    };
    let mut out = Vec::with_capacity(list.len());
    for (k, c) in list.iter().enumerate() {
        out.push(parse_constraint(
            file,
            &format!("constraints[{k}]"),
            c,
            dim,
        )?);
    }
    Ok(ConstraintFile {
        dim: file_dim,
        constraints: out,
    })
}

fn parse_constraint(
    file: &str,
    label: &str,
    v: &Value,
    dim: Option<usize>,
) -> Result<Constraint, InputError> {
    let Value::Object(o) = v else {
        return Err(err(
            file,
            label,
            format!("expected an object, found {}", kind_of(v)),
        ));
    };
    let node = match o.get("node") {
        None => return Err(err(file, format!("{label}.node"), "missing")),
        Some(n) => n.as_u64().ok_or_else(|| {
            err(
                file,
                format!("{label}.node"),
                format!("expected a node index (an integer ≥ 0), found {}", shown(n)),
            )
        })?,
    };
    let node = usize::try_from(node)
        .map_err(|_| err(file, format!("{label}.node"), "node index too large"))?;
    let kind = match o.get("kind") {
        None => {
            return Err(err(
                file,
                format!("{label}.kind"),
                format!("missing (expected {KINDS})"),
            ))
        }
        Some(Value::String(s)) => s.as_str(),
        Some(x) => {
            return Err(err(
                file,
                format!("{label}.kind"),
                format!("expected a string ({KINDS}), found {}", shown(x)),
            ))
        }
    };
    let allowed: &[&str] = match kind {
        "sticky" => &["displacement"],
        "plane" => &["normal", "offset"],
        "line" => &["direction", "offset"],
        "rows" => &["rows", "values"],
        other => {
            return Err(err(
                file,
                format!("{label}.kind"),
                format!(
                    "unknown kind '{}' (expected {KINDS})",
                    super::one_line(other, 60)
                ),
            ))
        }
    };
    check_keys(file, label, o, kind, allowed)?;
    let p = |key: &str| format!("{label}.{key}");
    let kind = match kind {
        "sticky" => ConstraintKind::Sticky {
            displacement: o
                .get("displacement")
                .map(|x| vector(file, &p("displacement"), x, dim))
                .transpose()?,
        },
        "plane" => {
            let normal = match o.get("normal") {
                Some(x) => vector(file, &p("normal"), x, dim)?,
                None => return Err(err(file, p("normal"), "missing (a plane needs its normal)")),
            };
            nonzero(file, &p("normal"), &normal)?;
            let offset = o
                .get("offset")
                .map(|x| number(file, &p("offset"), x))
                .transpose()?
                .unwrap_or(0.0);
            ConstraintKind::Plane { normal, offset }
        }
        "line" => {
            let direction = match o.get("direction") {
                Some(x) => vector(file, &p("direction"), x, dim)?,
                None => {
                    return Err(err(
                        file,
                        p("direction"),
                        "missing (a line needs its direction)",
                    ))
                }
            };
            nonzero(file, &p("direction"), &direction)?;
            let offset = o
                .get("offset")
                .map(|x| vector(file, &p("offset"), x, dim))
                .transpose()?;
            ConstraintKind::Line { direction, offset }
        }
        _ => {
            let rows = match o.get("rows") {
                Some(Value::Array(a)) if !a.is_empty() => a
                    .iter()
                    .enumerate()
                    .map(|(k, r)| {
                        let path = format!("{label}.rows[{k}]");
                        let r = vector(file, &path, r, dim)?;
                        nonzero(file, &path, &r)?;
                        Ok(r)
                    })
                    .collect::<Result<Vec<_>, InputError>>()?,
                Some(x) => {
                    return Err(err(
                        file,
                        p("rows"),
                        format!("expected a non-empty array of rows, found {}", shown(x)),
                    ))
                }
                None => return Err(err(file, p("rows"), "missing")),
            };
            let values = match o.get("values") {
                Some(x) => {
                    let v = vector(file, &p("values"), x, None)?;
                    if v.len() != rows.len() {
                        return Err(err(
                            file,
                            p("values"),
                            format!("has {} entries but there are {} rows", v.len(), rows.len()),
                        ));
                    }
                    v
                }
                None => vec![0.0; rows.len()],
            };
            ConstraintKind::Rows { rows, values }
        }
    };
    Ok(Constraint {
        node,
        kind,
        label: label.to_string(),
    })
}

fn check_keys(
    file: &str,
    label: &str,
    o: &Map<String, Value>,
    kind: &str,
    allowed: &[&str],
) -> Result<(), InputError> {
    for k in o.keys() {
        if k != "node" && k != "kind" && !allowed.contains(&k.as_str()) {
            return Err(err(
                file,
                format!("{label}.{}", super::one_line(k, 60)),
                format!(
                    "unknown key for kind {kind} (allowed: node, kind, {})",
                    allowed.join(", ")
                ),
            ));
        }
    }
    Ok(())
}

/// Reads bc.json from `path`.
pub fn read(path: &str, dim: Option<usize>) -> Result<ConstraintFile, InputError> {
    let text = super::read_text(path)?;
    parse(path, &text, dim)
}

/// The global form: B (m × dn, every row on one node) and p (m values, zero when absent)
/// become one `Rows` constraint per row, labelled `row k` (1-based as in the file);
/// `Frames::build` groups the rows of a node and ranks them.
pub fn constraints_from_matrix(
    b_file: &str,
    b: &mtx::Coo,
    p: Option<(&str, &[f64])>,
    dim: usize,
    nodes: usize,
) -> Result<Vec<Constraint>, InputError> {
    let nd = dim * nodes;
    if b.ncols != nd {
        return Err(err(
            b_file,
            format!("line {}", b.size_line),
            format!(
                "B has {} columns, expected {nd} = {dim} × {nodes} nodes",
                b.ncols
            ),
        ));
    }
    if let Some((pf, pv)) = p {
        if pv.len() != b.nrows {
            return Err(err(
                pf,
                "",
                format!(
                    "p has {} rows, expected {} (the rows of B)",
                    pv.len(),
                    b.nrows
                ),
            ));
        }
    }
    let m = b.nrows;
    let mut node_of: Vec<Option<usize>> = vec![None; m];
    let mut rows: Vec<Vec<f64>> = vec![vec![0.0; dim]; m];
    for &(r, c, v) in &b.entries {
        if v == 0.0 {
            continue; // an explicit zero couples nothing
        }
        let node = c / dim;
        match node_of[r] {
            None => node_of[r] = Some(node),
            Some(n) if n != node => {
                return Err(err(
                    b_file,
                    format!("row {}", r + 1),
                    format!(
                        "the row couples node {} and node {} (columns {} and {}); every row of B must touch exactly one node",
                        n.min(node),
                        n.max(node),
                        dim * n.min(node) + 1,
                        c + 1
                    ),
                ));
            }
            _ => {}
        }
        rows[r][c % dim] += v;
    }
    let mut out = Vec::with_capacity(m);
    for (r, row) in rows.into_iter().enumerate() {
        let Some(node) = node_of[r] else {
            return Err(err(
                b_file,
                format!("row {}", r + 1),
                "the row is empty (every row of B must touch exactly one node)",
            ));
        };
        // Each entry was finite as read; duplicates can sum past f64.
        if let Some(a) = row.iter().position(|x| !x.is_finite()) {
            return Err(err(
                b_file,
                format!("row {}", r + 1),
                format!(
                    "the duplicate entries in column {} sum to {}, which is not finite",
                    node * dim + a + 1,
                    row[a]
                ),
            ));
        }
        let value = p.map_or(0.0, |(_, pv)| pv[r]);
        if let Some((pf, _)) = p.filter(|_| !value.is_finite()) {
            return Err(err(
                pf,
                format!("row {}", r + 1),
                format!("p is {value}, which is not finite"),
            ));
        }
        out.push(Constraint {
            node,
            kind: ConstraintKind::Rows {
                rows: vec![row],
                values: vec![value],
            },
            label: format!("row {}", r + 1),
        });
    }
    Ok(out)
}

fn json_vec(v: &[f64]) -> Value {
    Value::Array(v.iter().map(|&x| Value::from(x)).collect())
}

/// One constraint as the JSON object of docs/formats.md, "Constraint JSON".
pub fn constraint_to_json(c: &Constraint) -> Value {
    let mut o = Map::new();
    o.insert("node".into(), Value::from(c.node));
    match &c.kind {
        ConstraintKind::Sticky { displacement } => {
            o.insert("kind".into(), "sticky".into());
            if let Some(d) = displacement {
                o.insert("displacement".into(), json_vec(d));
            }
        }
        ConstraintKind::Plane { normal, offset } => {
            o.insert("kind".into(), "plane".into());
            o.insert("normal".into(), json_vec(normal));
            o.insert("offset".into(), Value::from(*offset));
        }
        ConstraintKind::Line { direction, offset } => {
            o.insert("kind".into(), "line".into());
            o.insert("direction".into(), json_vec(direction));
            if let Some(off) = offset {
                o.insert("offset".into(), json_vec(off));
            }
        }
        ConstraintKind::Rows { rows, values } => {
            o.insert("kind".into(), "rows".into());
            o.insert(
                "rows".into(),
                Value::Array(rows.iter().map(|r| json_vec(r)).collect()),
            );
            o.insert("values".into(), json_vec(values));
        }
    }
    Value::Object(o)
}

/// Writes bc.json: one constraint per line (readable, and diff-friendly for big files).
/// serde_json writes the shortest decimal that reads back to the same f64.
pub fn write(
    path: impl AsRef<std::path::Path>,
    dim: usize,
    cs: &[Constraint],
) -> std::io::Result<()> {
    use std::io::Write;
    super::files::write_atomic(path, |w| {
        write!(w, "{{\"dim\": {dim}, \"constraints\": [")?;
        for (k, c) in cs.iter().enumerate() {
            let sep = if k + 1 < cs.len() { "," } else { "" };
            write!(w, "\n  {}{sep}", constraint_to_json(c))?;
        }
        writeln!(w, "\n]}}")
    })
}

/// The constraints as B (entries 0-based, m × dn) and p, one row per constrained
/// direction of each constraint (a line gives its constrained directions).
pub fn constraints_to_matrix(
    dim: usize,
    cs: &[Constraint],
) -> (Vec<(usize, usize, f64)>, Vec<f64>) {
    let mut b = Vec::new();
    let mut p = Vec::new();
    for c in cs {
        let (rows, vals) = node_rows(dim, c);
        for (row, val) in rows.into_iter().zip(vals) {
            let r = p.len();
            for (a, &x) in row.iter().enumerate() {
                if x != 0.0 {
                    b.push((r, c.node * dim + a, x));
                }
            }
            p.push(val);
        }
    }
    (b, p)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn design_example_parses() {
        let text = r#"{"dim": 3, "constraints": [
            {"node": 0, "kind": "sticky"},
            {"node": 1, "kind": "sticky", "displacement": [0.0, 0.1, 0.0]},
            {"node": 4, "kind": "plane", "normal": [0, 1, 0]},
            {"node": 5, "kind": "plane", "normal": [2, 3, 0], "offset": 0.0},
            {"node": 7, "kind": "line",  "direction": [1, 1, 0]},
            {"node": 9, "kind": "rows",  "rows": [[1, 0, 0], [0, 1, 1]], "values": [0, 0]}]}"#;
        let f = parse("bc.json", text, None).unwrap();
        assert_eq!(f.dim, Some(3));
        assert_eq!(f.constraints.len(), 6);
        assert_eq!(f.constraints[3].label, "constraints[3]");
        let back: Vec<Constraint> = f
            .constraints
            .iter()
            .map(|c| {
                let t = format!("{{\"constraints\": [{}]}}", constraint_to_json(c));
                let mut c2 = parse("x", &t, Some(3)).unwrap().constraints.remove(0);
                c2.label = c.label.clone();
                c2
            })
            .collect();
        assert_eq!(back, f.constraints);
    }

    #[test]
    fn faults_name_the_path() {
        let cases = [
            (r#"{"dim": 2, "constraints": [{"node": 0, "kind": "plane", "normal": [1e999, 0]}]}"#, "bc.json: constraints[0].normal[0]: 1e999 is not a finite number"),
            (r#"{"dim": 2, "constraints": [{"node": 0, "kind": "hinge"}]}"#, "bc.json: constraints[0].kind: unknown kind 'hinge' (expected sticky, plane, line or rows)"),
            (r#"{"dim": 2, "constraints": [{"node": 0, "kind": "sticky", "normal": [1, 0]}]}"#, "bc.json: constraints[0].normal: unknown key for kind sticky (allowed: node, kind, displacement)"),
            (r#"{"dim": 3, "constraints": [{"node": 0, "kind": "line", "direction": [1, 0]}]}"#, "bc.json: constraints[0].direction: has 2 components, expected 3 (dim is 3)"),
            ("{\"dim\": 2,\n \"constraints\": [}", "bc.json: line 2, column 18: malformed JSON: expected value"),
        ];
        for (text, want) in cases {
            assert_eq!(parse("bc.json", text, None).unwrap_err().to_string(), want);
        }
    }
}
