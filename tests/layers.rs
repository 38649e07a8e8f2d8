//! The library's layers, checked from its source: every module under `src/` names only
//! modules of its own layer or of the layers below it, and no two modules import each other,
//! directly or through others (test modules inside a file count as that file).
//!
//! Layers, lowest first (docs/architecture.md, "Layers of the crate"):
//!
//! | layer | folders                          |
//! |-------|----------------------------------|
//! | 0     | `error`                          |
//! | 1     | `core`, `io`, `cases`            |
//! | 2     | `solve`                          |
//! | 3     | `gpu`                            |
//! | 4     | `engine`                         |
//! | 5     | `sim`                            |
//! | 6     | `app`                            |
//!
//! `lib.rs` (the facade that re-exports the public names) and `main.rs` (the binary) stand
//! outside the layers. An import is any path a module names: `use` trees, inline paths
//! such as `crate::io::write(..)`, `super::`/`self::` paths and paths through a declared
//! child module; comments, doc links and string literals are not imports. A path through a
//! re-export (`crate::Problem`, `crate::solve::Precision`) counts as an import of the module
//! that defines the item.
//!
//! The checker is std-only so that it runs without the crate's features; its own tests
//! (`detects_*`) feed it small made-up trees with a known upward import and a known cycle.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The layer of a top-level folder (or file) of `src/`; `None`: outside the layers.
fn layer_of(top: &str) -> Option<usize> {
    match top {
        "error" => Some(0),
        "core" | "io" | "cases" => Some(1),
        "solve" => Some(2),
        "gpu" => Some(3),
        "engine" => Some(4),
        "sim" => Some(5),
        "app" => Some(6),
        _ => None,
    }
}

const LAYER_NAMES: [&str; 7] = [
    "error",
    "core/io/cases",
    "solve",
    "gpu",
    "engine",
    "sim",
    "app",
];

// ---------------------------------------------------------------------------------------
// Lexing: identifiers and the punctuation that paths are made of.
// ---------------------------------------------------------------------------------------

#[derive(Debug, Clone, PartialEq)]
enum Tok {
    Ident(String),
    PathSep,
    Open,
    Close,
    Comma,
    Semi,
    Star,
    Other(char),
}

/// Tokens of `src` with comments, string/char literals and attributes' contents kept out
/// of the way (an attribute's paths, e.g. `#[cfg(feature = "sim")]`, name no modules).
fn lex(src: &str) -> Vec<Tok> {
    lex_lines(src).into_iter().map(|(t, _)| t).collect()
}

/// [`lex`]'s tokens, each with the line (from 1) it starts on.
fn lex_lines(src: &str) -> Vec<(Tok, usize)> {
    let b: Vec<char> = src.chars().collect();
    // The line of each character, so a token's line costs nothing to find.
    let mut line_at = Vec::with_capacity(b.len());
    let mut line = 1;
    for &c in &b {
        line_at.push(line);
        if c == '\n' {
            line += 1;
        }
    }
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        // Comments (block comments nest in Rust).
        if c == '/' && b.get(i + 1) == Some(&'/') {
            while i < b.len() && b[i] != '\n' {
                i += 1;
            }
            continue;
        }
        if c == '/' && b.get(i + 1) == Some(&'*') {
            let mut depth = 0;
            while i < b.len() {
                if b[i] == '/' && b.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == '*' && b.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
            continue;
        }
        // Raw strings r"..", r#".."#, br#".."#.
        if (c == 'r' || (c == 'b' && b.get(i + 1) == Some(&'r'))) && !prev_is_ident(&b, i) {
            let mut j = if c == 'b' { i + 2 } else { i + 1 };
            let mut hashes = 0;
            while b.get(j) == Some(&'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) == Some(&'"') {
                j += 1;
                loop {
                    if j >= b.len() {
                        break;
                    }
                    if b[j] == '"' && (0..hashes).all(|k| b.get(j + 1 + k) == Some(&'#')) {
                        j += 1 + hashes;
                        break;
                    }
                    j += 1;
                }
                i = j;
                continue;
            }
        }
        if c == '"' {
            i += 1;
            while i < b.len() && b[i] != '"' {
                if b[i] == '\\' {
                    i += 1;
                }
                i += 1;
            }
            i += 1;
            continue;
        }
        if c == '\'' {
            // A char literal ('a', '\n', '\u{..}') or a lifetime ('a): a literal closes
            // within a few characters.
            if b.get(i + 1) == Some(&'\\') {
                let mut j = i + 2;
                while j < b.len() && b[j] != '\'' {
                    j += 1;
                }
                i = j + 1;
                continue;
            }
            if b.get(i + 2) == Some(&'\'') {
                i += 3;
                continue;
            }
            i += 1;
            continue;
        }
        if c == '#' && (b.get(i + 1) == Some(&'[') || b.get(i + 1) == Some(&'!')) {
            // Skip the attribute's bracket group.
            let mut j = i + 1;
            while j < b.len() && b[j] != '[' {
                j += 1;
            }
            let mut depth = 0;
            while j < b.len() {
                match b[j] {
                    '[' => depth += 1,
                    ']' => {
                        depth -= 1;
                        if depth == 0 {
                            break;
                        }
                    }
                    '"' => {
                        j += 1;
                        while j < b.len() && b[j] != '"' {
                            if b[j] == '\\' {
                                j += 1;
                            }
                            j += 1;
                        }
                    }
                    _ => {}
                }
                j += 1;
            }
            i = j + 1;
            continue;
        }
        if c.is_alphabetic() || c == '_' {
            let start = i;
            while i < b.len() && (b[i].is_alphanumeric() || b[i] == '_') {
                i += 1;
            }
            let word: String = b[start..i].iter().collect();
            let word = word.strip_prefix("r#").map(str::to_string).unwrap_or(word);
            out.push((Tok::Ident(word), line_at[start]));
            continue;
        }
        if c.is_ascii_digit() {
            let start = i;
            while i < b.len() && (b[i].is_alphanumeric() || b[i] == '_' || b[i] == '.') {
                if b[i] == '.' && !b.get(i + 1).is_some_and(|d| d.is_ascii_digit()) {
                    break;
                }
                i += 1;
            }
            out.push((Tok::Other('0'), line_at[start]));
            continue;
        }
        if c == ':' && b.get(i + 1) == Some(&':') {
            out.push((Tok::PathSep, line_at[i]));
            i += 2;
            continue;
        }
        if !c.is_whitespace() {
            let tok = match c {
                '{' => Tok::Open,
                '}' => Tok::Close,
                ',' => Tok::Comma,
                ';' => Tok::Semi,
                '*' => Tok::Star,
                other => Tok::Other(other),
            };
            out.push((tok, line_at[i]));
        }
        i += 1;
    }
    out
}

fn prev_is_ident(b: &[char], i: usize) -> bool {
    i > 0 && (b[i - 1].is_alphanumeric() || b[i - 1] == '_')
}

// ---------------------------------------------------------------------------------------
// Modules and the paths they name.
// ---------------------------------------------------------------------------------------

/// One path named in a file: the module it is named from (the file's module plus any
/// inline `mod x { .. }` around it) and its segments; `glob` for `use a::b::*`.
#[derive(Debug, Clone)]
struct Named {
    scope: Vec<String>,
    segments: Vec<String>,
    /// `pub use` (a re-export) and the name it is exported under.
    export_as: Option<String>,
    is_use: bool,
    line_hint: String,
}

/// What one file declares and names.
#[derive(Debug, Default)]
struct FileInfo {
    /// Child modules declared (`mod x;` or `mod x { .. }`), by the scope that declares them.
    children: BTreeSet<Vec<String>>,
    named: Vec<Named>,
}

fn scan(module: &[String], src: &str) -> FileInfo {
    let toks = lex(src);
    let mut info = FileInfo::default();
    // Scopes: (module path, brace depth at which its block closes).
    let mut scopes: Vec<(Vec<String>, usize)> = vec![(module.to_vec(), usize::MAX)];
    let mut depth = 0usize;
    let mut i = 0;
    while i < toks.len() {
        let scope = scopes.last().map(|s| s.0.clone()).unwrap_or_default();
        match &toks[i] {
            Tok::Open => {
                depth += 1;
                i += 1;
            }
            Tok::Close => {
                if scopes.len() > 1 && scopes.last().is_some_and(|s| s.1 == depth) {
                    scopes.pop();
                }
                depth = depth.saturating_sub(1);
                i += 1;
            }
            Tok::Ident(w) if w == "mod" => {
                if let Some(Tok::Ident(name)) = toks.get(i + 1) {
                    let mut child = scope.clone();
                    child.push(name.clone());
                    info.children.insert(child.clone());
                    if toks.get(i + 2) == Some(&Tok::Open) {
                        depth += 1;
                        scopes.push((child, depth));
                        i += 3;
                        continue;
                    }
                }
                i += 2;
            }
            Tok::Ident(w) if w == "use" => {
                let is_pub = i > 0 && matches!(&toks[i - 1], Tok::Ident(p) if p == "pub")
                    || (i > 3
                        && matches!(&toks[i - 1], Tok::Other(')'))
                        && matches!(&toks[i - 4], Tok::Ident(p) if p == "pub"));
                let mut j = i + 1;
                let mut leaves = Vec::new();
                parse_use_tree(&toks, &mut j, Vec::new(), &mut leaves);
                for (segments, alias) in leaves {
                    let export_as = if is_pub {
                        alias.or_else(|| segments.last().cloned())
                    } else {
                        None
                    };
                    info.named.push(Named {
                        scope: scope.clone(),
                        line_hint: format!("use {}", segments.join("::")),
                        segments,
                        export_as,
                        is_use: true,
                    });
                }
                i = j;
            }
            Tok::Ident(first) => {
                // An inline path: ident (:: ident)+.
                let after_sep = i > 0 && toks[i - 1] == Tok::PathSep;
                if !after_sep && toks.get(i + 1) == Some(&Tok::PathSep) {
                    let mut segments = vec![first.clone()];
                    let mut j = i + 1;
                    while toks.get(j) == Some(&Tok::PathSep) {
                        match toks.get(j + 1) {
                            Some(Tok::Ident(s)) => {
                                segments.push(s.clone());
                                j += 2;
                            }
                            _ => break,
                        }
                    }
                    info.named.push(Named {
                        scope: scope.clone(),
                        line_hint: segments.join("::"),
                        segments,
                        export_as: None,
                        is_use: false,
                    });
                    i = j;
                } else {
                    i += 1;
                }
            }
            _ => i += 1,
        }
    }
    info
}

/// Parses a use tree from `toks[*j]` up to its `;` (or the `,`/`}` that ends a nested one),
/// collecting (path, alias) leaves; a glob leaf ends in `*`.
fn parse_use_tree(
    toks: &[Tok],
    j: &mut usize,
    prefix: Vec<String>,
    leaves: &mut Vec<(Vec<String>, Option<String>)>,
) {
    let mut path = prefix;
    loop {
        match toks.get(*j) {
            Some(Tok::PathSep) => *j += 1,
            Some(Tok::Ident(w)) if w == "as" => {
                let alias = match toks.get(*j + 1) {
                    Some(Tok::Ident(a)) => Some(a.clone()),
                    _ => None,
                };
                *j += 2;
                leaves.push((std::mem::take(&mut path), alias));
                return;
            }
            Some(Tok::Ident(w)) => {
                path.push(w.clone());
                *j += 1;
            }
            Some(Tok::Star) => {
                path.push("*".to_string());
                *j += 1;
                leaves.push((std::mem::take(&mut path), None));
                return;
            }
            Some(Tok::Open) => {
                *j += 1;
                loop {
                    match toks.get(*j) {
                        Some(Tok::Close) => {
                            *j += 1;
                            break;
                        }
                        Some(Tok::Comma) => *j += 1,
                        None => return,
                        _ => parse_use_tree(toks, j, path.clone(), leaves),
                    }
                }
                return;
            }
            Some(Tok::Semi) | Some(Tok::Comma) | Some(Tok::Close) | None => {
                if !path.is_empty() {
                    leaves.push((std::mem::take(&mut path), None));
                }
                if toks.get(*j) == Some(&Tok::Semi) {
                    *j += 1;
                }
                return;
            }
            Some(_) => {
                *j += 1;
            }
        }
    }
}

/// The crate as the checker sees it: files by module path.
struct Tree {
    /// Module path → file (relative to `src/`), for file modules.
    files: BTreeMap<Vec<String>, String>,
    info: BTreeMap<Vec<String>, FileInfo>,
    /// Every module path, file or inline.
    modules: BTreeSet<Vec<String>>,
    /// Module path → the file module that holds it.
    holder: BTreeMap<Vec<String>, Vec<String>>,
}

impl Tree {
    fn new(sources: &[(String, String)]) -> Tree {
        let mut files = BTreeMap::new();
        let mut info = BTreeMap::new();
        let mut modules = BTreeSet::new();
        let mut holder = BTreeMap::new();
        for (rel, src) in sources {
            let Some(module) = module_of(rel) else {
                continue;
            };
            let fi = scan(&module, src);
            modules.insert(module.clone());
            holder.insert(module.clone(), module.clone());
            for child in &fi.children {
                modules.insert(child.clone());
                holder
                    .entry(child.clone())
                    .or_insert_with(|| module.clone());
            }
            files.insert(module.clone(), rel.clone());
            info.insert(module, fi);
        }
        // Children declared inline live in their declaring file; children declared with
        // `mod x;` have a file of their own (inserted above, which wins).
        for m in files.keys() {
            holder.insert(m.clone(), m.clone());
        }
        Tree {
            files,
            info,
            modules,
            holder,
        }
    }

    /// The file module that holds `module` (the deepest enclosing file module).
    fn file_of(&self, module: &[String]) -> Vec<String> {
        let mut m = module.to_vec();
        loop {
            if let Some(h) = self.holder.get(&m) {
                return h.clone();
            }
            if m.pop().is_none() {
                return Vec::new();
            }
        }
    }

    /// Re-exports of `module`: exported name → (scope, source path).
    fn reexport(&self, module: &[String], name: &str) -> Option<(Vec<String>, Vec<String>)> {
        let file = self.file_of(module);
        let fi = self.info.get(&file)?;
        fi.named
            .iter()
            .find(|n| n.scope == module && n.export_as.as_deref() == Some(name))
            .map(|n| (n.scope.clone(), n.segments.clone()))
    }

    /// Module aliases a scope brings in with `use` (`use crate::io;` → `io`).
    fn alias(&self, scope: &[String], name: &str) -> Option<Vec<String>> {
        let file = self.file_of(scope);
        let fi = self.info.get(&file)?;
        for n in fi.named.iter().filter(|n| n.is_use && n.scope == scope) {
            if n.segments.last().map(String::as_str) == Some(name) && n.segments.len() > 1 {
                let target = self.resolve_start(scope, &n.segments, 0)?;
                if self.modules.contains(&target.0) && target.1 == n.segments.len() {
                    return Some(target.0);
                }
            }
        }
        None
    }

    /// Resolves the leading module part of `segments` named from `scope`: the module
    /// reached and how many segments it used; `None` when the path starts outside the
    /// crate (std, a dependency, a local item).
    fn resolve_start(
        &self,
        scope: &[String],
        segments: &[String],
        depth: usize,
    ) -> Option<(Vec<String>, usize)> {
        if depth > 8 {
            return None;
        }
        let mut cur: Vec<String>;
        let mut k = 0;
        match segments.first().map(String::as_str) {
            Some("crate") => {
                cur = Vec::new();
                k = 1;
            }
            Some("self") => {
                cur = scope.to_vec();
                k = 1;
            }
            Some("super") => {
                cur = scope.to_vec();
                while segments.get(k).map(String::as_str) == Some("super") {
                    cur.pop()?;
                    k += 1;
                }
            }
            Some(first) => {
                let mut child = scope.to_vec();
                child.push(first.to_string());
                if self.modules.contains(&child) {
                    cur = child;
                    k = 1;
                } else if let Some(target) = self.alias(scope, first) {
                    cur = target;
                    k = 1;
                } else {
                    return None;
                }
            }
            None => return None,
        }
        while let Some(s) = segments.get(k) {
            let mut next = cur.clone();
            next.push(s.clone());
            if self.modules.contains(&next) {
                cur = next;
                k += 1;
                continue;
            }
            // An item: follow a re-export to the module that defines it.
            if let Some((rscope, rpath)) = self.reexport(&cur, s) {
                if let Some((m, used)) = self.resolve_start(&rscope, &rpath, depth + 1) {
                    if used == rpath.len() && self.modules.contains(&m) {
                        // A re-exported module: go on inside it.
                        cur = m;
                        k += 1;
                        continue;
                    }
                    return Some((m, k + 1));
                }
            }
            break;
        }
        Some((cur, k))
    }

    /// Edges between file modules: (from, to) → an example of the path named.
    fn edges(&self) -> BTreeMap<(Vec<String>, Vec<String>), String> {
        let mut edges = BTreeMap::new();
        for (file, fi) in &self.info {
            for n in &fi.named {
                let Some((target, _)) = self.resolve_start(&n.scope, &n.segments, 0) else {
                    continue;
                };
                let to = self.file_of(&target);
                if &to != file {
                    edges
                        .entry((file.clone(), to))
                        .or_insert_with(|| n.line_hint.clone());
                }
            }
        }
        edges
    }
}

fn module_of(rel: &str) -> Option<Vec<String>> {
    let rel = rel.strip_suffix(".rs")?;
    let mut parts: Vec<String> = rel.split('/').map(str::to_string).collect();
    if parts == ["main"] {
        return None;
    }
    if parts == ["lib"] {
        return Some(Vec::new());
    }
    if parts.last().map(String::as_str) == Some("mod") {
        parts.pop();
    }
    Some(parts)
}

fn name(m: &[String]) -> String {
    if m.is_empty() {
        "crate (lib.rs)".to_string()
    } else {
        m.join("::")
    }
}

/// Every violation: upward imports, then cycles among modules and among top-level modules
/// (strongly connected components).
fn check(sources: &[(String, String)]) -> Vec<String> {
    let tree = Tree::new(sources);
    let edges = tree.edges();
    let mut problems = Vec::new();
    for (module, file) in &tree.files {
        if !module.is_empty() && layer_of(&module[0]).is_none() {
            problems.push(format!(
                "{file} is in no layer: move it into a layer's folder"
            ));
        }
    }
    for ((from, to), example) in &edges {
        let (Some(lf), Some(lt)) = (
            from.first().and_then(|t| layer_of(t)),
            to.first().and_then(|t| layer_of(t)),
        ) else {
            continue;
        };
        if lt > lf {
            problems.push(format!(
                "upward import: {} (layer {} {}) names {} (layer {} {}) in `{}`",
                name(from),
                lf,
                LAYER_NAMES[lf],
                name(to),
                lt,
                LAYER_NAMES[lt],
                example
            ));
        }
    }
    // Cycles among the layered modules (lib.rs, the facade, stands outside).
    let nodes: Vec<Vec<String>> = tree
        .files
        .keys()
        .filter(|m| !m.is_empty())
        .cloned()
        .collect();
    let index: BTreeMap<&Vec<String>, usize> =
        nodes.iter().enumerate().map(|(i, m)| (m, i)).collect();
    let mut adj = vec![Vec::new(); nodes.len()];
    for (from, to) in edges.keys() {
        if let (Some(&a), Some(&b)) = (index.get(from), index.get(to)) {
            adj[a].push(b);
        }
    }
    for comp in strongly_connected(&adj) {
        if comp.len() > 1 {
            let cycle = shortest_cycle(&adj, &comp);
            let steps: Vec<String> = cycle
                .windows(2)
                .map(|w| {
                    let ex = &edges[&(nodes[w[0]].clone(), nodes[w[1]].clone())];
                    format!(
                        "{} -> {} (`{}`)",
                        name(&nodes[w[0]]),
                        name(&nodes[w[1]]),
                        ex
                    )
                })
                .collect();
            let mut members: Vec<String> = comp.iter().map(|&i| name(&nodes[i])).collect();
            members.sort();
            problems.push(format!(
                "import cycle: {} [{} modules import each other: {}]",
                steps.join(", "),
                comp.len(),
                members.join(", ")
            ));
        }
    }
    problems.extend(top_level_cycles(&edges));
    problems
}

/// Cycles among the top-level modules (`core -> cases -> core`), which no two files need
/// to close: a test module of `core` naming `cases` while `cases` names `core` is one.
fn top_level_cycles(edges: &BTreeMap<(Vec<String>, Vec<String>), String>) -> Vec<String> {
    let mut tops: BTreeSet<&String> = BTreeSet::new();
    for (from, to) in edges.keys() {
        tops.extend(from.first());
        tops.extend(to.first());
    }
    let tops: Vec<&String> = tops.into_iter().collect();
    let index: BTreeMap<&String, usize> = tops.iter().enumerate().map(|(i, t)| (*t, i)).collect();
    let mut adj = vec![Vec::new(); tops.len()];
    // One example import per top-level edge, the first in path order.
    let mut example: BTreeMap<(usize, usize), String> = BTreeMap::new();
    for ((from, to), ex) in edges {
        let (Some(f), Some(t)) = (from.first(), to.first()) else {
            continue;
        };
        let (a, b) = (index[f], index[t]);
        if a != b && !adj[a].contains(&b) {
            adj[a].push(b);
            example.insert((a, b), format!("{} -> {} (`{ex}`)", name(from), name(to)));
        }
    }
    let mut problems = Vec::new();
    for comp in strongly_connected(&adj) {
        if comp.len() > 1 {
            let cycle = shortest_cycle(&adj, &comp);
            let steps: Vec<String> = cycle
                .windows(2)
                .map(|w| example[&(w[0], w[1])].clone())
                .collect();
            let mut members: Vec<&str> = comp.iter().map(|&i| tops[i].as_str()).collect();
            members.sort();
            problems.push(format!(
                "top-level import cycle: {} [{} top-level modules import each other: {}]",
                steps.join(", "),
                comp.len(),
                members.join(", ")
            ));
        }
    }
    problems
}

/// The shortest cycle inside one strongly connected component, as a closed node list.
fn shortest_cycle(adj: &[Vec<usize>], comp: &[usize]) -> Vec<usize> {
    let members: BTreeSet<usize> = comp.iter().copied().collect();
    let mut best: Option<Vec<usize>> = None;
    for &start in comp {
        // Breadth-first from `start` back to `start`, inside the component.
        let mut prev: BTreeMap<usize, usize> = BTreeMap::new();
        let mut queue = std::collections::VecDeque::from([start]);
        let mut found = None;
        'bfs: while let Some(v) = queue.pop_front() {
            for &w in &adj[v] {
                if !members.contains(&w) {
                    continue;
                }
                if w == start {
                    found = Some(v);
                    break 'bfs;
                }
                if let std::collections::btree_map::Entry::Vacant(e) = prev.entry(w) {
                    e.insert(v);
                    queue.push_back(w);
                }
            }
        }
        if let Some(last) = found {
            let mut path = vec![start, last];
            let mut v = last;
            while v != start {
                v = prev[&v];
                path.push(v);
            }
            path.reverse();
            if best.as_ref().is_none_or(|b| path.len() < b.len()) {
                best = Some(path);
            }
        }
    }
    best.unwrap_or_default()
}

/// Tarjan's strongly connected components (iterative).
fn strongly_connected(adj: &[Vec<usize>]) -> Vec<Vec<usize>> {
    let n = adj.len();
    let mut index = vec![usize::MAX; n];
    let mut low = vec![0; n];
    let mut on_stack = vec![false; n];
    let mut stack = Vec::new();
    let mut comps = Vec::new();
    let mut next = 0;
    for root in 0..n {
        if index[root] != usize::MAX {
            continue;
        }
        let mut work = vec![(root, 0usize)];
        index[root] = next;
        low[root] = next;
        next += 1;
        stack.push(root);
        on_stack[root] = true;
        while let Some(&mut (v, ref mut e)) = work.last_mut() {
            if *e < adj[v].len() {
                let w = adj[v][*e];
                *e += 1;
                if index[w] == usize::MAX {
                    index[w] = next;
                    low[w] = next;
                    next += 1;
                    stack.push(w);
                    on_stack[w] = true;
                    work.push((w, 0));
                } else if on_stack[w] {
                    low[v] = low[v].min(index[w]);
                }
            } else {
                work.pop();
                if let Some(&(u, _)) = work.last() {
                    low[u] = low[u].min(low[v]);
                }
                if low[v] == index[v] {
                    let mut comp = Vec::new();
                    while let Some(w) = stack.pop() {
                        on_stack[w] = false;
                        comp.push(w);
                        if w == v {
                            break;
                        }
                    }
                    comps.push(comp);
                }
            }
        }
    }
    comps
}

fn read_tree(root: &Path) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut stack: Vec<PathBuf> = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("reading {}: {e}", dir.display()))
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let rel = p
                    .strip_prefix(root)
                    .expect("under src")
                    .to_string_lossy()
                    .replace('\\', "/");
                let src = std::fs::read_to_string(&p)
                    .unwrap_or_else(|e| panic!("reading {}: {e}", p.display()));
                out.push((rel, src));
            }
        }
    }
    out
}

#[test]
fn the_library_has_no_upward_imports_and_no_cycles() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let sources = read_tree(&src);
    assert!(
        sources.len() > 20,
        "found only {} files under src/",
        sources.len()
    );
    let problems = check(&sources);
    assert!(
        problems.is_empty(),
        "{} layer problem(s):\n  {}",
        problems.len(),
        problems.join("\n  ")
    );
}

fn tree(files: &[(&str, &str)]) -> Vec<(String, String)> {
    files
        .iter()
        .map(|(p, s)| (p.to_string(), s.to_string()))
        .collect()
}

#[test]
fn detects_an_upward_import() {
    let sources = tree(&[
        ("lib.rs", "pub mod core; pub mod sim;"),
        ("core/mod.rs", "pub mod problem;"),
        (
            "core/problem.rs",
            "use crate::sim::scene::Scene; pub struct P;",
        ),
        ("sim/mod.rs", "pub mod scene;"),
        ("sim/scene.rs", "pub struct Scene;"),
    ]);
    let problems = check(&sources);
    assert_eq!(problems.len(), 1, "{problems:?}");
    assert!(
        problems[0].contains("upward import: core::problem"),
        "{problems:?}"
    );
}

#[test]
fn detects_an_inline_upward_path_but_not_one_in_a_comment_or_string() {
    let ok = tree(&[
        ("lib.rs", "pub mod core; pub mod app;"),
        ("core/mod.rs", "pub mod a;"),
        (
            "core/a.rs",
            "// crate::app::cli::run()\n/// [`crate::app::cli`]\nfn f() { let s = \"crate::app::cli::x\"; }",
        ),
        ("app/mod.rs", "pub mod cli;"),
        ("app/cli.rs", "pub fn run() {}"),
    ]);
    assert!(check(&ok).is_empty(), "{:?}", check(&ok));
    let bad = tree(&[
        ("lib.rs", "pub mod core; pub mod app;"),
        ("core/mod.rs", "pub mod a;"),
        ("core/a.rs", "fn f() { crate::app::cli::run(); }"),
        ("app/mod.rs", "pub mod cli;"),
        ("app/cli.rs", "pub fn run() {}"),
    ]);
    let problems = check(&bad);
    assert_eq!(problems.len(), 1, "{problems:?}");
}

#[test]
fn detects_a_cycle_through_a_reexport_and_inside_a_test_module() {
    let sources = tree(&[
        ("lib.rs", "pub mod solve;"),
        ("solve/mod.rs", "pub mod cg; pub mod fused; pub use cg::Cg;"),
        (
            "solve/cg.rs",
            "pub struct Cg; pub fn go() { super::fused::run() }",
        ),
        (
            "solve/fused.rs",
            "pub fn run() {}\n#[cfg(test)]\nmod tests { use crate::solve::Cg; }",
        ),
    ]);
    let problems = check(&sources);
    assert_eq!(problems.len(), 1, "{problems:?}");
    assert!(
        problems[0].contains("2 modules import each other"),
        "{problems:?}"
    );
    assert!(
        problems[0].contains("solve::fused -> solve::cg"),
        "{problems:?}"
    );
}

#[test]
fn a_facade_that_only_reexports_makes_no_cycle() {
    let sources = tree(&[
        ("lib.rs", "pub mod solve; pub use solve::Cg;"),
        (
            "solve/mod.rs",
            "mod cg; mod fused; pub use cg::Cg; pub use fused::run;",
        ),
        (
            "solve/cg.rs",
            "pub struct Cg; pub fn go() { crate::solve::run() }",
        ),
        ("solve/fused.rs", "pub fn run() {}"),
    ]);
    assert!(check(&sources).is_empty(), "{:?}", check(&sources));
}

/// The calls that move bytes between host and device, wait on it, submit work or begin a
/// compute pass. `gpu::context` wraps each once (`write_buffer`, `buffer_init`,
/// `download_many`, `wait`, `submit`, `compute_pass`), counting the bytes and waits and
/// timing the passes for the run's profile; anywhere else they would move or wait unseen.
const RAW_DEVICE_CALLS: [&str; 6] = [
    "queue.write_buffer(",
    "create_buffer_init(",
    "map_async(",
    ".poll(",
    "queue.submit(",
    "begin_compute_pass(",
];

/// Where a raw call stands outside the context on purpose: the device CG's per-kernel
/// timing writes its own timestamps around each dispatch (a measurement, its reads counted
/// through the context).
const RAW_ALLOWED: [(&str, &str); 1] = [("gpu/pcg/cg/profile.rs", "begin_compute_pass(")];

/// Every raw device call in `sources` outside gpu/context.rs and the allowed ones, as
/// "file:line: call" (comments do not count).
fn raw_device_calls(sources: &[(String, String)]) -> Vec<String> {
    let mut out = Vec::new();
    for (rel, src) in sources {
        if rel == "gpu/context.rs" {
            continue;
        }
        for (k, line) in src.lines().enumerate() {
            let code = line.split("//").next().unwrap_or_default();
            for call in RAW_DEVICE_CALLS {
                let allowed = RAW_ALLOWED.iter().any(|&(f, c)| f == rel && c == call);
                if code.contains(call) && !allowed {
                    out.push(format!("{rel}:{}: {call}", k + 1));
                }
            }
        }
    }
    out
}

/// Every transfer, wait, submit and compute pass of the library goes through the
/// context, so `gpu.host_to_device_bytes`, `device_to_host_bytes`, `host_syncs` and the
/// profile's phases see all of them.
#[test]
fn every_transfer_and_wait_goes_through_the_counted_context() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let raw = raw_device_calls(&read_tree(&src));
    assert!(
        raw.is_empty(),
        "device calls outside gpu::context:\n  {}",
        raw.join("\n  ")
    );
}

#[test]
fn detects_a_raw_device_call_but_not_one_in_a_comment() {
    let files = tree(&[
        (
            "gpu/context.rs",
            "fn w(&self) { self.queue.write_buffer(b, 0, d); }",
        ),
        (
            "sim/device/ops.rs",
            "// self.ctx.queue.submit([enc.finish()]);\nfn f() { ctx.queue.submit([e]); }",
        ),
    ]);
    assert_eq!(
        raw_device_calls(&files),
        ["sim/device/ops.rs:2: queue.submit("]
    );
}

#[test]
fn detects_a_top_level_cycle_through_a_test_module() {
    let sources = tree(&[
        ("lib.rs", "pub mod core; pub mod cases;"),
        ("core/mod.rs", "pub mod elimination; pub mod sparse;"),
        ("core/sparse.rs", "pub struct BlockCsr;"),
        (
            "core/elimination.rs",
            "pub fn apply() {}\n#[cfg(test)]\nmod tests { use crate::cases::generate::random; }",
        ),
        ("cases/mod.rs", "pub mod generate;"),
        (
            "cases/generate.rs",
            "use crate::core::sparse::BlockCsr; pub fn random() -> BlockCsr { BlockCsr }",
        ),
    ]);
    let problems = check(&sources);
    assert_eq!(problems.len(), 1, "{problems:?}");
    assert!(
        problems[0].contains("2 top-level modules import each other: cases, core"),
        "{problems:?}"
    );
    assert!(
        problems[0].contains("core::elimination -> cases::generate"),
        "{problems:?}"
    );
}

// ---------------------------------------------------------------------------------------
// Sizes: functions and files short enough to read whole.
// ---------------------------------------------------------------------------------------

/// The most lines a function of `src/` may span, from its `fn` line to its closing brace.
const MAX_FUNCTION_LINES: usize = 150;

/// The most lines a file of `src/` may hold.
const MAX_FILE_LINES: usize = 1200;

/// Every function in `src` (one file) with its name, first line and line count, found by
/// matching braces over [`lex_lines`]'s tokens, so braces in comments, strings and char
/// literals do not count. A function is `fn name` up to its body's closing brace; a
/// declaration without a body (`fn f();` in a trait) is none.
fn function_spans(src: &str) -> Vec<(String, usize, usize)> {
    let toks = lex_lines(src);
    let mut out = Vec::new();
    for (k, (tok, line)) in toks.iter().enumerate() {
        let (Tok::Ident(kw), Some((Tok::Ident(name), _))) = (tok, toks.get(k + 1)) else {
            continue;
        };
        if kw != "fn" {
            continue;
        }
        // The body opens at the first `{` outside the signature's brackets; a `;` there
        // (outside `[T; N]`) ends a bodiless declaration.
        let mut nest = 0i64;
        let mut open = None;
        for (j, (t, _)) in toks.iter().enumerate().skip(k + 2) {
            match t {
                Tok::Other('(') | Tok::Other('[') => nest += 1,
                Tok::Other(')') | Tok::Other(']') => nest -= 1,
                Tok::Semi if nest == 0 => break,
                Tok::Open if nest == 0 => {
                    open = Some(j);
                    break;
                }
                _ => {}
            }
        }
        let Some(open) = open else { continue };
        let mut depth = 0usize;
        for (t, end) in &toks[open..] {
            match t {
                Tok::Open => depth += 1,
                Tok::Close => {
                    depth -= 1;
                    if depth == 0 {
                        out.push((name.clone(), *line, end - line + 1));
                        break;
                    }
                }
                _ => {}
            }
        }
    }
    out
}

/// Every function longer than [`MAX_FUNCTION_LINES`] and every file longer than
/// [`MAX_FILE_LINES`], as "file:line: fn name: N lines" and "file: N lines".
fn oversized(sources: &[(String, String)]) -> Vec<String> {
    let mut out = Vec::new();
    for (rel, src) in sources {
        let lines = src.lines().count();
        if lines > MAX_FILE_LINES {
            out.push(format!("{rel}: {lines} lines (at most {MAX_FILE_LINES})"));
        }
        for (name, line, len) in function_spans(src) {
            if len > MAX_FUNCTION_LINES {
                out.push(format!(
                    "{rel}:{line}: fn {name}: {len} lines (at most {MAX_FUNCTION_LINES})"
                ));
            }
        }
    }
    out
}

/// No function of the library is longer than [`MAX_FUNCTION_LINES`] and no file longer
/// than [`MAX_FILE_LINES`]: each can be read whole before it is changed.
#[test]
fn no_function_or_file_of_the_library_is_too_long() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let long = oversized(&read_tree(&src));
    assert!(
        long.is_empty(),
        "{} function(s) or file(s) too long:\n  {}",
        long.len(),
        long.join("\n  ")
    );
}

#[test]
fn measures_functions_by_their_braces_not_those_in_comments_strings_or_chars() {
    let src = "\
trait T {
    fn declared(&self, a: [u8; 3]);
}
fn short(a: [u8; 2]) -> usize {
    // a } in a comment
    let s = \"}}}\"; /* { */
    let c = '}';
    let r = r#\"{\"#;
    a.len() + s.len() + r.len() + (c as usize)
}
fn outer<'a>(x: &'a str) -> impl Fn() + 'a {
    fn inner() {}
    move || {
        inner();
        let _ = x;
    }
}
";
    assert_eq!(
        function_spans(src),
        [
            ("short".to_string(), 4, 7),
            ("outer".to_string(), 11, 7),
            ("inner".to_string(), 12, 1),
        ]
    );
    let body: String = (0..MAX_FUNCTION_LINES - 2).map(|_| "    f();\n").collect();
    let at_limit = format!("fn fits() {{\n{body}}}\n");
    let over = format!("fn over() {{\n{body}    f();\n}}\n");
    let files = tree(&[("a.rs", at_limit.as_str()), ("b.rs", over.as_str())]);
    assert_eq!(
        oversized(&files),
        [format!(
            "b.rs:1: fn over: {} lines (at most {MAX_FUNCTION_LINES})",
            MAX_FUNCTION_LINES + 1
        )]
    );
    let long_file = "\n".repeat(MAX_FILE_LINES + 1);
    assert_eq!(
        oversized(&tree(&[("c.rs", long_file.as_str())])),
        [format!(
            "c.rs: {} lines (at most {MAX_FILE_LINES})",
            MAX_FILE_LINES + 1
        )]
    );
}
