//! The documents name only what exists:
//!
//! - every repository path in README.md, BENCHMARKS.md, STABILITY.md, python/README.md
//!   and docs/**/*.md (markdown links, and paths under src/, tests/, docs/, scripts/ and
//!   the other top folders, in backticks, code blocks and prose) is on disk, and so is
//!   every such path named in the sources (src/, tests/, examples/, benches/, scripts/,
//!   python/, .ci/, shaders/);
//! - every `stickslip SUBCOMMAND --option` the documents name (in code blocks and
//!   backticks) is a subcommand and option of the command line's clap definition, and
//!   every subcommand has a section in docs/cli.md; every `cargo … --example/--bench/--test
//!   NAME` names a file of examples/, benches/ or tests/;
//! - every scene key in the tables of docs/scenes.md is a key the scene parser knows,
//!   every key it knows has a row there, and every whole scene a document shows (a toml
//!   code block that sets `dimension`) parses;
//! - every reference to a section of a document (`DOC.md, "Section"`), in the documents
//!   and the sources, names a heading (or a paragraph opening in bold) of that document.
//!
//! docs/lab/ holds dated records of runs as they were made: only their markdown links are
//! checked (navigation), not the commands and paths of their date.
//!
//! The checkers take the text; the `detects_*` tests feed them a broken path, an unknown
//! subcommand, an unknown option, a missing cargo target, an unknown scene key, a missing
//! section and a scene that does not parse, and expect each to be reported.
#![cfg(feature = "cli")]

use clap::CommandFactory;
use std::path::{Path, PathBuf};

/// Top folders whose paths a document may name in backticks or code blocks.
const REPO_DIRS: [&str; 11] = [
    "src/",
    "tests/",
    "docs/",
    "scripts/",
    "benches/",
    "python/",
    "examples/",
    "scenes/",
    "shaders/",
    ".ci/",
    "fuzz/",
];

/// One broken reference: the document, its line (1-based) and what is wrong.
#[derive(Debug, Clone, PartialEq)]
struct Problem {
    doc: String,
    line: usize,
    what: String,
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}: {}", self.doc, self.line, self.what)
    }
}

/// A piece of code in a document: an inline backtick span or one logical line of a code
/// block (lines continued with `\` joined), with the line it starts on.
#[derive(Debug, Clone)]
struct Code {
    line: usize,
    text: String,
    inline: bool,
}

/// Inline code spans and code-block lines of a markdown text. Fenced blocks (```) and
/// lines indented by four spaces outside lists count as code blocks.
fn code_pieces(text: &str) -> Vec<Code> {
    let mut out = Vec::new();
    let mut fenced = false;
    let mut pending: Option<Code> = None;
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let trimmed = raw.trim_start();
        if trimmed.starts_with("```") {
            fenced = !fenced;
            continue;
        }
        let block = fenced
            || pending.is_some()
            || (raw.starts_with("    ") && !trimmed.starts_with(['-', '*', '|']));
        if block {
            let (body, continued) = match raw.trim_end().strip_suffix('\\') {
                Some(b) => (b, true),
                None => (raw, false),
            };
            let piece = match pending.take() {
                Some(mut p) => {
                    p.text.push(' ');
                    p.text.push_str(body.trim());
                    p
                }
                None => Code {
                    line,
                    text: body.trim().to_string(),
                    inline: false,
                },
            };
            if continued {
                pending = Some(piece);
            } else {
                out.push(piece);
            }
            continue;
        }
        if let Some(p) = pending.take() {
            out.push(p);
        }
        let mut rest = raw;
        while let Some(start) = rest.find('`') {
            let ticks = rest[start..].chars().take_while(|&c| c == '`').count();
            let fence = &rest[start..start + ticks];
            let after = &rest[start + ticks..];
            match after.find(fence) {
                Some(end) => {
                    out.push(Code {
                        line,
                        text: after[..end].trim().to_string(),
                        inline: true,
                    });
                    rest = &after[end + ticks..];
                }
                None => break,
            }
        }
    }
    if let Some(p) = pending {
        out.push(p);
    }
    out
}

/// Targets of markdown links `[text](target)` with their lines: relative paths only
/// (no URL, no in-page anchor), the `#anchor` cut off.
fn link_targets(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let mut rest = line;
        while let Some(p) = rest.find("](") {
            let after = &rest[p + 2..];
            let Some(end) = after.find(')') else { break };
            let target = after[..end].trim();
            rest = &after[end..];
            if target.is_empty()
                || target.starts_with('#')
                || target.contains("://")
                || target.starts_with("mailto:")
            {
                continue;
            }
            let path = target.split('#').next().unwrap_or(target);
            out.push((i + 1, path.to_string()));
        }
    }
    out
}

/// Repository paths named in a piece of code: tokens that start with one of [`REPO_DIRS`]
/// (or `./` then one of them), without placeholders or globs.
fn repo_paths(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    for tok in code.split(|c: char| c.is_whitespace() || "()[]\"',;`=".contains(c)) {
        let tok = tok.trim_start_matches("./");
        let tok = tok.trim_end_matches(['.', ':', ',']);
        if !REPO_DIRS.iter().any(|d| tok.starts_with(d)) {
            continue;
        }
        if tok.contains(['*', '<', '>', '{', '}', '$', '…']) || tok.contains("..") {
            continue;
        }
        out.push(tok.to_string());
    }
    out
}

/// Broken paths of one document: markdown links relative to the document's folder, and
/// (`code_paths`) repository paths in code and prose relative to the repository root.
fn check_paths(doc: &str, text: &str, root: &Path, code_paths: bool) -> Vec<Problem> {
    let mut out = Vec::new();
    let dir = root.join(doc);
    let dir = dir.parent().unwrap_or(root);
    let links = link_targets(text);
    for (line, target) in &links {
        if !dir.join(target).exists() {
            out.push(Problem {
                doc: doc.to_string(),
                line: *line,
                what: format!("link target `{target}` does not exist"),
            });
        }
    }
    if code_paths {
        // Code first (a code block's continued line counts once), then the prose lines.
        // A link's target was checked above, relative to the document.
        let mut seen: std::collections::BTreeSet<(usize, String)> = links.iter().cloned().collect();
        let pieces = code_pieces(text).into_iter().map(|c| (c.line, c.text));
        let lines = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.to_string()));
        for (line, t) in pieces.chain(lines) {
            for p in repo_paths(&t) {
                if !root.join(&p).exists() && seen.insert((line, p.clone())) {
                    out.push(Problem {
                        doc: doc.to_string(),
                        line,
                        what: format!("path `{p}` does not exist"),
                    });
                }
            }
        }
    }
    out
}

/// Repository paths named in a source file (its comments and strings) that do not exist.
fn check_source_paths(file: &str, text: &str, root: &Path) -> Vec<Problem> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        for p in repo_paths(line) {
            if !root.join(&p).exists() {
                out.push(Problem {
                    doc: file.to_string(),
                    line: i + 1,
                    what: format!("path `{p}` does not exist"),
                });
            }
        }
    }
    out
}

/// Cargo targets named in a document's code that do not exist: `--example NAME`,
/// `--bench NAME` and `--test NAME` need examples/NAME.rs, benches/NAME.rs and
/// tests/NAME.rs.
fn check_cargo_targets(doc: &str, text: &str, root: &Path) -> Vec<Problem> {
    let mut out = Vec::new();
    for piece in code_pieces(text) {
        let toks: Vec<&str> = piece.text.split_whitespace().collect();
        if !toks.contains(&"cargo") {
            continue;
        }
        for w in toks.windows(2) {
            let folder = match w[0] {
                "--example" => "examples",
                "--bench" => "benches",
                "--test" => "tests",
                _ => continue,
            };
            let name = w[1].trim_end_matches(|c: char| !(c.is_ascii_alphanumeric() || c == '_'));
            if name.is_empty()
                || name.starts_with('-')
                || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            {
                continue;
            }
            let file = format!("{folder}/{name}.rs");
            if !root.join(&file).exists() {
                out.push(Problem {
                    doc: doc.to_string(),
                    line: piece.line,
                    what: format!("`{} {name}`: {file} does not exist", w[0]),
                });
            }
        }
    }
    out
}

/// Whether a token names the binary: `stickslip` or a path ending in `/stickslip`.
fn is_binary(tok: &str) -> bool {
    tok == "stickslip"
        || (tok.ends_with("/stickslip")
            && tok
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "/._-".contains(c)))
}

/// Where a command line of the binary starts in `toks`: the index of its first argument
/// after `stickslip` or after `cargo run ... --` (not `--example`/`--bench`), or, for an
/// inline span (`inline_sub`), a span that starts with a subcommand followed by an option.
fn command_starts(toks: &[&str], subcommands: &[String], inline_sub: bool) -> Vec<usize> {
    let mut starts = Vec::new();
    for (i, t) in toks.iter().enumerate() {
        if is_binary(t) && i + 1 < toks.len() && !toks[i + 1].starts_with("--stickslip") {
            starts.push(i + 1);
        }
        if *t == "cargo" && toks.get(i + 1) == Some(&"run") {
            let tail = &toks[i + 2..];
            let end = tail
                .iter()
                .position(|t| is_separator(t))
                .unwrap_or(tail.len());
            let tail = &tail[..end];
            if tail
                .iter()
                .any(|t| *t == "--example" || *t == "--bench" || *t == "--bin")
            {
                continue;
            }
            if let Some(k) = tail.iter().position(|t| *t == "--") {
                if k + 1 < tail.len() {
                    starts.push(i + 2 + k + 1);
                }
            }
        }
    }
    if inline_sub
        && starts.is_empty()
        && toks.len() >= 2
        && subcommands.iter().any(|s| s == toks[0])
        && toks[1].starts_with("--")
    {
        starts.push(0);
    }
    starts
}

/// Shell punctuation that ends a command line.
fn is_separator(t: &str) -> bool {
    matches!(t, "|" | "||" | "&&" | ";" | ">" | ">>" | "2>&1") || t.starts_with('#')
}

/// Subcommands and long options the documents may name, from the clap definition.
struct CliSpec {
    cmd: clap::Command,
}

impl CliSpec {
    fn new() -> Self {
        let mut cmd = stickslip::app::cli::Cli::command();
        cmd.build();
        CliSpec { cmd }
    }

    fn subcommand_names(&self) -> Vec<String> {
        self.cmd
            .get_subcommands()
            .map(|c| c.get_name().to_string())
            .filter(|n| n != "help")
            .collect()
    }
}

/// Long options of a command (globals propagated by `build`), plus help and version.
fn long_options(cmd: &clap::Command) -> Vec<String> {
    let mut v: Vec<String> = cmd
        .get_arguments()
        .flat_map(|a| {
            let mut names: Vec<String> = a.get_long().map(str::to_string).into_iter().collect();
            names.extend(
                a.get_all_aliases()
                    .unwrap_or_default()
                    .iter()
                    .map(|s| s.to_string()),
            );
            names
        })
        .collect();
    v.extend(["help".to_string(), "version".to_string()]);
    v
}

/// Unknown subcommands and options in the command lines of one document.
fn check_commands(doc: &str, text: &str, cli: &CliSpec) -> Vec<Problem> {
    let subs = cli.subcommand_names();
    let mut out = Vec::new();
    for piece in code_pieces(text) {
        let toks: Vec<&str> = piece.text.split_whitespace().collect();
        for start in command_starts(&toks, &subs, piece.inline) {
            let mut cmd = &cli.cmd;
            let mut path = vec!["stickslip".to_string()];
            let mut k = start;
            let mut unknown_sub = false;
            // Walk down the subcommands the line names.
            while let Some(t) = toks.get(k) {
                if t.starts_with('-') || is_separator(t) {
                    break;
                }
                match cmd.find_subcommand(t) {
                    Some(sub) => {
                        cmd = sub;
                        path.push(t.to_string());
                        k += 1;
                    }
                    None => {
                        let word = t.trim_end_matches(['.', ',', ':', ')']);
                        let looks_like_sub = cmd.has_subcommands()
                            && path.len() == 1
                            && !word.is_empty()
                            && word.chars().all(|c| c.is_ascii_lowercase() || c == '-');
                        if looks_like_sub {
                            unknown_sub = true;
                            out.push(Problem {
                                doc: doc.to_string(),
                                line: piece.line,
                                what: format!("`stickslip {word}` is not a subcommand"),
                            });
                        }
                        break;
                    }
                }
            }
            if unknown_sub {
                continue;
            }
            let longs = long_options(cmd);
            for t in &toks[k..] {
                if is_separator(t) {
                    break;
                }
                let Some(name) = t.strip_prefix("--") else {
                    continue;
                };
                let name = name.split('=').next().unwrap_or(name);
                let name = name.trim_end_matches(|c: char| !c.is_ascii_alphanumeric());
                if name.is_empty() || !name.starts_with(|c: char| c.is_ascii_lowercase()) {
                    continue;
                }
                if !longs.iter().any(|l| l == name) {
                    out.push(Problem {
                        doc: doc.to_string(),
                        line: piece.line,
                        what: format!("`{} --{name}` is not an option", path.join(" ")),
                    });
                }
            }
        }
    }
    out
}

/// Scene keys in the first column of the tables whose header's first cell is `key`:
/// (line, table or `""` for the top level, whether it is an array of tables, key).
fn scene_keys(text: &str) -> Vec<(usize, String, bool, String)> {
    let mut out = Vec::new();
    let mut in_table = false;
    for (i, line) in text.lines().enumerate() {
        let t = line.trim();
        if !t.starts_with('|') {
            in_table = false;
            continue;
        }
        let first = t.trim_matches('|').split('|').next().unwrap_or("").trim();
        if !in_table {
            in_table = first == "key";
            continue;
        }
        if first.chars().all(|c| c == '-' || c == ':') {
            continue;
        }
        for piece in code_pieces(first) {
            let s = piece.text.trim();
            let (table, array, key) = if let Some(r) = s.strip_prefix("[[") {
                match r.split_once("]]") {
                    Some((tb, k)) => (tb.trim(), true, k.trim()),
                    None => continue,
                }
            } else if let Some(r) = s.strip_prefix('[') {
                match r.split_once(']') {
                    Some((tb, k)) => (tb.trim(), false, k.trim()),
                    None => continue,
                }
            } else {
                ("", false, s)
            };
            out.push((i + 1, table.to_string(), array, key.to_string()));
        }
    }
    out
}

/// A scene that parses, bodies last so that a key can be added to its body.
const MINIMAL_SCENE: &str = r#"dimension = 2
time_step = 0.01
steps = 1

[[bodies]]
mesh = { kind = "rectangle", size = [1.0, 1.0], cells = [2, 2] }
material = { model = "neo-hookean", young = 1e5, poisson = 0.3, density = 1000.0 }
"#;

/// Whether the scene parser rejects `key` in `table` as unknown. The key is given a
/// string value: a known key may then fail on its type or on a duplicate, which is not
/// what this asks.
fn scene_key_unknown(table: &str, array: bool, key: &str) -> bool {
    let line = format!("{key} = \"x\"\n");
    let text = match (table, array) {
        ("", _) => format!("{line}{MINIMAL_SCENE}"),
        ("bodies", true) => format!("{MINIMAL_SCENE}{line}"),
        (t, true) => format!("{MINIMAL_SCENE}\n[[{t}]]\n{line}"),
        (t, false) => format!("{MINIMAL_SCENE}\n[{t}]\n{line}"),
    };
    match stickslip::sim::scene::parse(&text, "probe.toml", 1.0) {
        Ok(_) => false,
        Err(e) => {
            let msg = e.to_string();
            msg.contains("unknown field")
        }
    }
}

/// The keys the scene parser accepts in `table` (`""`: the top level), read from its
/// message for an unknown key ("unknown field `…`, expected one of `a`, `b`, …").
fn schema_keys(table: &str, array: bool) -> Vec<String> {
    let probe = "zz_not_a_key";
    let line = format!("{probe} = 1\n");
    let text = match (table, array) {
        ("", _) => format!("{line}{MINIMAL_SCENE}"),
        ("bodies", true) => format!("{MINIMAL_SCENE}{line}"),
        (t, true) => format!("{MINIMAL_SCENE}\n[[{t}]]\n{line}"),
        (t, false) => format!("{MINIMAL_SCENE}\n[{t}]\n{line}"),
    };
    let Err(e) = stickslip::sim::scene::parse(&text, "probe.toml", 1.0) else {
        return Vec::new();
    };
    let msg = e.to_string();
    let Some(list) = msg.split("expected").nth(1) else {
        return Vec::new();
    };
    list.split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect()
}

/// The tables of a scene file, as docs/scenes.md names them.
const SCENE_TABLES: [(&str, bool); 7] = [
    ("", false),
    ("output", false),
    ("solver", false),
    ("moving", false),
    ("bodies", true),
    ("boundary", true),
    ("obstacle", true),
];

/// Scene keys of docs/scenes.md's tables that the parser does not know.
fn check_scene_keys(doc: &str, text: &str) -> Vec<Problem> {
    let mut out = Vec::new();
    for (line, table, array, key) in scene_keys(text) {
        if scene_key_unknown(&table, array, &key) {
            let shown = match (table.as_str(), array) {
                ("", _) => key.clone(),
                (t, true) => format!("[[{t}]] {key}"),
                (t, false) => format!("[{t}] {key}"),
            };
            out.push(Problem {
                doc: doc.to_string(),
                line,
                what: format!("scene key `{shown}` is not in the scene schema"),
            });
        }
    }
    out
}

/// A document's text with each line's comment marker (`//!`, `///`, `//`, `#`) taken off
/// for source files, the lines joined by spaces, and the byte offset where each line starts.
fn joined(text: &str, source: bool) -> (String, Vec<usize>) {
    let mut out = String::new();
    let mut starts = Vec::new();
    for line in text.lines() {
        starts.push(out.len());
        let mut l = line.trim();
        if source {
            for m in ["//!", "///", "//", "#"] {
                if let Some(r) = l.strip_prefix(m) {
                    l = r.trim_start();
                    break;
                }
            }
        }
        out.push_str(l);
        out.push(' ');
    }
    (out, starts)
}

/// References to a section of a markdown file: `FILE.md, "Section"`, `FILE.md "Section"`,
/// `FILE.md ("Section")` and `[..](FILE.md), "Section"`, as (line, file, section).
fn section_refs(text: &str, source: bool) -> Vec<(usize, String, String)> {
    let (t, starts) = joined(text, source);
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(k) = t[from..].find(".md") {
        let end = from + k + 3;
        from = end;
        let start = t[..end - 3]
            .rfind(|c: char| !(c.is_ascii_alphanumeric() || "_./-".contains(c)))
            .map_or(0, |i| i + 1);
        let file = &t[start..end];
        if file.len() <= 3 {
            continue;
        }
        let rest = t[end..].trim_start_matches(')');
        let quoted = [", \"", " \"", " (\""]
            .iter()
            .find_map(|p| rest.strip_prefix(p));
        let Some(q) = quoted else { continue };
        let Some(close) = q.find('"') else { continue };
        let section = q[..close].trim();
        if section.is_empty() || section.len() > 120 {
            continue;
        }
        let line = starts.partition_point(|&s| s <= start);
        out.push((line, file.to_string(), section.to_string()));
    }
    out
}

/// Whether a markdown text has a heading, or a paragraph opening in bold, that holds
/// `section` (case aside).
fn has_section(text: &str, section: &str) -> bool {
    let want = section.to_lowercase();
    text.lines().any(|l| {
        let l = l.trim_start();
        (l.starts_with('#') || l.starts_with("**")) && l.to_lowercase().contains(&want)
    })
}

/// References to sections that the named file does not have. `doc` is the referring file
/// (relative to `root`): a name resolves against its folder, then against the root.
fn check_sections(doc: &str, text: &str, root: &Path) -> Vec<Problem> {
    let source = !doc.ends_with(".md");
    let dir = root.join(doc);
    let dir = dir.parent().unwrap_or(root).to_path_buf();
    let mut out = Vec::new();
    for (line, file, section) in section_refs(text, source) {
        let target = [dir.join(&file), root.join(&file)]
            .into_iter()
            .find(|p| p.is_file());
        let Some(target) = target else { continue };
        let Ok(body) = std::fs::read_to_string(&target) else {
            continue;
        };
        if !has_section(&body, &section) {
            out.push(Problem {
                doc: doc.to_string(),
                line,
                what: format!("{file} has no section \"{section}\""),
            });
        }
    }
    out
}

/// Source files that may name a document's section: every file under these folders.
fn source_files(root: &Path) -> Vec<String> {
    let mut files = Vec::new();
    let mut stack: Vec<PathBuf> = [
        "src", "tests", "examples", "benches", "scripts", "python", ".ci", "shaders",
    ]
    .iter()
    .map(|d| root.join(d))
    .collect();
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p
                .extension()
                .is_some_and(|x| ["rs", "py", "sh", "wgsl", "toml"].iter().any(|e| x == *e))
                || p.file_name().is_some_and(|n| n == "run")
            {
                if let Ok(rel) = p.strip_prefix(root) {
                    files.push(rel.to_string_lossy().replace('\\', "/"));
                }
            }
        }
    }
    files.sort();
    files
}

/// Whole scenes in a document: the ```toml code blocks that set `dimension`, with the line
/// each starts on.
fn toml_scenes(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut block: Option<(usize, String)> = None;
    for (i, line) in text.lines().enumerate() {
        let t = line.trim_start();
        match block.as_mut() {
            None if t.starts_with("```toml") => block = Some((i + 2, String::new())),
            Some(_) if t.starts_with("```") => {
                if let Some((line, body)) = block.take() {
                    if body
                        .lines()
                        .any(|l| l.trim_start().starts_with("dimension"))
                    {
                        out.push((line, body));
                    }
                }
            }
            Some((_, body)) => {
                body.push_str(line);
                body.push('\n');
            }
            None => {}
        }
    }
    out
}

/// Whole scenes of a document that the scene parser refuses, with its message.
fn check_toml_scenes(doc: &str, text: &str) -> Vec<Problem> {
    toml_scenes(text)
        .into_iter()
        .filter_map(|(line, body)| {
            stickslip::sim::scene::parse(&body, "scene.toml", 1.0)
                .err()
                .map(|e| Problem {
                    doc: doc.to_string(),
                    line,
                    what: format!("the scene does not parse: {e}"),
                })
        })
        .collect()
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The documents, relative to the root: the top-level ones and every .md under docs/.
fn documents(root: &Path) -> Vec<String> {
    let mut docs: Vec<String> = [
        "README.md",
        "BENCHMARKS.md",
        "STABILITY.md",
        "python/README.md",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let mut stack = vec![root.join("docs")];
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "md") {
                if let Ok(rel) = p.strip_prefix(root) {
                    docs.push(rel.to_string_lossy().replace('\\', "/"));
                }
            }
        }
    }
    docs.sort();
    docs
}

fn is_lab(doc: &str) -> bool {
    doc.starts_with("docs/lab/")
}

#[test]
fn every_document_names_what_exists() {
    let root = root();
    let cli = CliSpec::new();
    let mut problems = Vec::new();
    let docs = documents(&root);
    assert!(docs.len() > 5, "found only {docs:?}");
    for doc in &docs {
        let text = std::fs::read_to_string(root.join(doc))
            .unwrap_or_else(|e| panic!("{doc}: cannot read: {e}"));
        problems.extend(check_paths(doc, &text, &root, !is_lab(doc)));
        if !is_lab(doc) {
            problems.extend(check_commands(doc, &text, &cli));
            problems.extend(check_cargo_targets(doc, &text, &root));
        }
        if !is_lab(doc) {
            problems.extend(check_sections(doc, &text, &root));
            problems.extend(check_toml_scenes(doc, &text));
        }
        if doc == "docs/scenes.md" {
            let keys = scene_keys(&text);
            assert!(keys.len() > 20, "docs/scenes.md: found only {keys:?}");
            problems.extend(check_scene_keys(doc, &text));
        }
    }
    for file in source_files(&root) {
        let Ok(text) = std::fs::read_to_string(root.join(&file)) else {
            continue;
        };
        problems.extend(check_sections(&file, &text, &root));
        // This file's own tests name broken paths on purpose.
        if file != "tests/doc_references.rs" {
            problems.extend(check_source_paths(&file, &text, &root));
        }
    }
    let list: Vec<String> = problems.iter().map(|p| p.to_string()).collect();
    assert!(
        list.is_empty(),
        "{} broken references:\n{}",
        list.len(),
        list.join("\n")
    );
}

#[test]
fn every_subcommand_has_a_section_in_cli_md() {
    let text = std::fs::read_to_string(root().join("docs/cli.md")).expect("docs/cli.md");
    let headings: Vec<&str> = text.lines().filter(|l| l.starts_with('#')).collect();
    for sub in CliSpec::new().subcommand_names() {
        let name = format!("`stickslip {sub}`");
        assert!(
            headings.iter().any(|h| h.contains(&name)),
            "docs/cli.md has no section headed {name}"
        );
    }
}

#[test]
fn every_scene_key_has_a_row_in_scenes_md() {
    let text = std::fs::read_to_string(root().join("docs/scenes.md")).expect("docs/scenes.md");
    let rows: Vec<(String, bool, String)> = scene_keys(&text)
        .into_iter()
        .map(|(_, t, a, k)| (t, a, k))
        .collect();
    let mut missing = Vec::new();
    for (table, array) in SCENE_TABLES {
        let keys = schema_keys(table, array);
        assert!(!keys.is_empty(), "no keys read for table {table:?}");
        for key in keys {
            if !rows
                .iter()
                .any(|(t, a, k)| t == table && *a == array && *k == key)
            {
                missing.push(match (table, array) {
                    ("", _) => key,
                    (t, true) => format!("[[{t}]] {key}"),
                    (t, false) => format!("[{t}] {key}"),
                });
            }
        }
    }
    // The top level's tables are the sections of the key table, not rows of their own.
    missing.retain(|k| !SCENE_TABLES.iter().any(|(t, _)| !t.is_empty() && k == t));
    assert!(
        missing.is_empty(),
        "docs/scenes.md has no row for {missing:?}"
    );
}

#[test]
fn detects_a_broken_path() {
    let text = "See [the method](method.md) and [gone](nowhere.md).\n\n\
                The CG is in `src/solve/cg.rs`; the old one was `src/solve/no_such_file.rs`.\n\n    \
                scripts/petsc_solve.py ex\n    python scripts/not_a_script.py ex\n";
    let p = check_paths("docs/probe.md", text, &root(), true);
    let what: Vec<&str> = p.iter().map(|p| p.what.as_str()).collect();
    assert_eq!(
        what,
        [
            "link target `nowhere.md` does not exist",
            "path `src/solve/no_such_file.rs` does not exist",
            "path `scripts/not_a_script.py` does not exist",
        ],
        "{p:?}"
    );
    assert_eq!(p[0].line, 1);
    assert_eq!(p[2].line, 6);
    let src = "//! The device side of `Stepper` (src/sim/integrator/stepper.rs,\n\
               //! shaders/newton_ops.wgsl); the CPU's in src/integrator.rs.\n";
    let p = check_source_paths("src/probe.rs", src, &root());
    let what: Vec<&str> = p.iter().map(|p| p.what.as_str()).collect();
    assert_eq!(what, ["path `src/integrator.rs` does not exist"], "{p:?}");
    assert_eq!(p[0].line, 2);
}

#[test]
fn detects_an_unknown_subcommand_and_option() {
    let cli = CliSpec::new();
    let text = "Run `stickslip run twist --size 2 --no-such-option 3`.\n\n    \
                stickslip solve --hessian H.mtx \\\n        --gradient g.mtx --tolerence 1e-8\n    \
                cargo run --release -- bench --quick --fast\n    stickslip frobnicate --x\n\n\
                As `solve --coarse none` or `run --frames 3`.\n";
    let p = check_commands("docs/probe.md", text, &cli);
    let what: Vec<&str> = p.iter().map(|p| p.what.as_str()).collect();
    assert_eq!(
        what,
        [
            "`stickslip run --no-such-option` is not an option",
            "`stickslip solve --tolerence` is not an option",
            "`stickslip bench --fast` is not an option",
            "`stickslip frobnicate` is not a subcommand",
            "`stickslip run --frames` is not an option",
        ],
        "{p:?}"
    );
    assert_eq!(p[1].line, 3);
    let text = "    cargo run --release --example gpu_measure -- 216000\n    \
                cargo run --release --example no_such_example\n    \
                cargo test --release --test layers --test no_such_test\n";
    let p = check_cargo_targets("docs/probe.md", text, &root());
    let what: Vec<&str> = p.iter().map(|p| p.what.as_str()).collect();
    assert_eq!(
        what,
        [
            "`--example no_such_example`: examples/no_such_example.rs does not exist",
            "`--test no_such_test`: tests/no_such_test.rs does not exist",
        ],
        "{p:?}"
    );
}

#[test]
fn detects_an_unknown_scene_key() {
    let text = "| key | meaning |\n|---|---|\n\
                | `dimension` | 2 or 3 |\n\
                | `steps` / `end_time` | one of them |\n\
                | `[solver] cg_tolerance` | tolerance |\n\
                | `[solver] cg_tolerence` | misspelt |\n\
                | `[[bodies]] velocity` | initial velocity |\n\
                | `[[boundary]] kind` | sticky, plane, line |\n\
                | `[[boundary]] speed` | not a key |\n\
                | `frames` | not a key |\n";
    let p = check_scene_keys("docs/scenes.md", text);
    let what: Vec<&str> = p.iter().map(|p| p.what.as_str()).collect();
    assert_eq!(
        what,
        [
            "scene key `[solver] cg_tolerence` is not in the scene schema",
            "scene key `[[boundary]] speed` is not in the scene schema",
            "scene key `frames` is not in the scene schema",
        ],
        "{p:?}"
    );
}

#[test]
fn detects_a_reference_to_a_missing_section() {
    let md = "See [cli.md](cli.md), \"Exit codes\", and method.md, \"The\nno such section\".\n";
    let p = check_sections("docs/probe.md", md, &root());
    let what: Vec<&str> = p.iter().map(|p| p.what.as_str()).collect();
    assert_eq!(
        what,
        ["method.md has no section \"The no such section\""],
        "{p:?}"
    );
    assert_eq!(p[0].line, 1);
    let rs = "//! The CG (BENCHMARKS.md, \"CPU CG against\n//! SciPy's Jacobi CG\") and docs/method.md (\"Nowhere\").\n";
    let p = check_sections("src/probe.rs", rs, &root());
    let what: Vec<&str> = p.iter().map(|p| p.what.as_str()).collect();
    assert_eq!(what, ["docs/method.md has no section \"Nowhere\""], "{p:?}");
}

#[test]
fn detects_a_scene_that_does_not_parse() {
    let ok = "dimension = 2\ntime_step = 0.01\nsteps = 1\n[[bodies]]\n\
              mesh = { kind = \"rectangle\", size = [1.0, 1.0], cells = [2, 2] }\n\
              material = { model = \"neo-hookean\", young = 1e5, poisson = 0.3, density = 1.0 }\n";
    let bad = ok.replace("time_step", "timestep");
    let text = format!("A scene:\n\n```toml\n{ok}```\n\nAnother:\n\n```toml\n{bad}```\n");
    let p = check_toml_scenes("docs/probe.md", &text);
    assert_eq!(p.len(), 1, "{p:?}");
    assert_eq!(p[0].line, 15);
    assert!(p[0].what.contains("timestep"), "{p:?}");
}
