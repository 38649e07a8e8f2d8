//! Output safety: an output never destroys an input, never looks complete when it is
//! not, and never sits beside stale files of another run.
//!
//! - [`check_outputs`]: before any work, every output path is checked: it is not the same
//!   file as an input or as another output (device and inode, after resolving links, so
//!   symlinks and hard links are caught), it is not a folder, and its folder exists and
//!   accepts new files.
//! - [`write_atomic`]: a result file is written to a temporary file in the same folder and
//!   renamed into place, so a killed process leaves the old file or the new one, never a
//!   truncated one under the final name. (A device such as `/dev/null` is written in
//!   place.) No fsync: this guards against a killed process, not against power loss.
//! - [`OutputDir`]: a command owns its output folder. A manifest
//!   (`.stickslip-<command>.manifest`) lists what the command wrote there; the next run of
//!   the same command removes those files (and nothing else) before writing. Files with
//!   the command's output names that no manifest lists (a folder written by hand, or by an
//!   older version) are refused unless `overwrite` is set. A lock (`.stickslip.lock`, an
//!   advisory `flock` the kernel drops when the process dies) makes a second concurrent
//!   run into the same folder refuse at once.

use crate::error::InputError;
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// The name of the lock file inside an owned output folder.
pub const LOCK_FILE: &str = ".stickslip.lock";

/// Marks the temporary files of [`write_atomic`]: `.<name>.stickslip-tmp-<pid>-<k>`.
const TMP_MARK: &str = ".stickslip-tmp-";

/// Most symbolic links followed when resolving one path (as Linux's ELOOP limit).
const MAX_LINKS: usize = 40;

/// What identifies a file on disk: (device, inode) on Unix; elsewhere the canonical path.
#[derive(Debug, Clone, PartialEq, Eq)]
enum FileId {
    #[cfg(unix)]
    Inode(u64, u64),
    #[allow(dead_code)]
    Path(PathBuf),
}

/// The identity of an existing file (links followed), None when it does not exist.
fn file_id(path: &Path) -> Option<FileId> {
    let meta = std::fs::metadata(path).ok()?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let _ = path;
        Some(FileId::Inode(meta.dev(), meta.ino()))
    }
    #[cfg(not(unix))]
    {
        let _ = meta;
        std::fs::canonicalize(path).ok().map(FileId::Path)
    }
}

/// `path` with every symbolic link in its last component followed, so that a write goes
/// to the link's target and the link stays. A path that is not a link is returned as is.
pub fn resolve_links(path: &Path) -> std::io::Result<PathBuf> {
    let mut p = path.to_path_buf();
    for _ in 0..MAX_LINKS {
        match std::fs::symlink_metadata(&p) {
            Ok(m) if m.file_type().is_symlink() => {
                let t = std::fs::read_link(&p)?;
                p = if t.is_absolute() {
                    t
                } else {
                    parent_of(&p).join(t)
                };
            }
            _ => return Ok(p),
        }
    }
    Err(std::io::Error::other("too many levels of symbolic links"))
}

/// The folder a file path is in (`.` for a bare name).
fn parent_of(p: &Path) -> PathBuf {
    match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// A key naming where a (perhaps not yet existing) file lives: its folder's canonical
/// path joined with its name. Two outputs with the same key are the same file.
fn location_key(resolved: &Path) -> Option<PathBuf> {
    let dir = std::fs::canonicalize(parent_of(resolved)).ok()?;
    Some(dir.join(resolved.file_name()?))
}

/// An input or output of a command: the option that names it and its path.
#[derive(Debug, Clone, Copy)]
pub struct Named<'a> {
    pub option: &'a str,
    pub path: &'a Path,
}

impl<'a> Named<'a> {
    pub fn new(option: &'a str, path: &'a (impl AsRef<Path> + ?Sized)) -> Self {
        Named {
            option,
            path: path.as_ref(),
        }
    }
}

/// The inputs' identities, for the checks.
struct InputIds(Vec<(String, FileId)>);

impl InputIds {
    fn new(inputs: &[Named]) -> Self {
        InputIds(
            inputs
                .iter()
                .filter_map(|i| {
                    let shown = format!("{} ({})", i.option, i.path.display());
                    file_id(i.path).map(|id| (shown, id))
                })
                .collect(),
        )
    }

    /// The input `path` is the same file as, if any.
    fn same_as(&self, path: &Path) -> Option<&str> {
        let id = file_id(path)?;
        self.0
            .iter()
            .find(|(_, i)| *i == id)
            .map(|(s, _)| s.as_str())
    }
}

/// Checks, before any work, that every output can be written without harm: not the same
/// file as an input or another output (links resolved, device and inode compared), not a
/// folder, in a folder that exists and accepts new files. The error names the output, its
/// option and the fault (exit 2 on the command line).
pub fn check_outputs(inputs: &[Named], outputs: &[Named]) -> Result<(), InputError> {
    let ids = InputIds::new(inputs);
    let mut seen: Vec<(String, Option<PathBuf>, Option<FileId>)> = Vec::new();
    for o in outputs {
        let shown = o.path.display().to_string();
        let fail = |problem: String| Err(InputError::new(&shown, o.option, problem));
        let resolved = match resolve_links(o.path) {
            Ok(p) => p,
            Err(e) => return fail(format!("cannot resolve the path: {e}")),
        };
        if let Some(input) = ids.same_as(&resolved) {
            return fail(format!(
                "is the same file as the input {input}; writing it would destroy the input"
            ));
        }
        let meta = std::fs::metadata(&resolved).ok();
        if meta.as_ref().is_some_and(|m| m.is_dir()) {
            return fail("is a folder, not a file".into());
        }
        // A rename would replace a read-only file where writing into it was refused.
        if meta
            .as_ref()
            .is_some_and(|m| m.is_file() && m.permissions().readonly())
        {
            return fail("is read-only".into());
        }
        let key = location_key(&resolved);
        let id = file_id(&resolved);
        if let Some((other, _, _)) = seen
            .iter()
            .find(|(_, k, i)| (key.is_some() && *k == key) || (id.is_some() && *i == id))
        {
            return fail(format!(
                "is the same file as the output {other}; one would overwrite the other"
            ));
        }
        seen.push((format!("{} ({shown})", o.option), key, id));
        // A device or a pipe (`/dev/null`, `/dev/stdout`) is written in place.
        if meta.as_ref().is_some_and(|m| !m.is_file()) {
            continue;
        }
        let dir = parent_of(&resolved);
        probe_folder(&dir).map_err(|problem| InputError::new(&shown, o.option, problem))?;
        if let Some(problem) = held_by_another(&dir) {
            return fail(problem);
        }
    }
    Ok(())
}

/// When another live process holds `dir`'s lock (a `run` writing there): the problem, as
/// [`take_lock`] words it. The lock file is only read, never created, and a lock this
/// process holds is its own.
fn held_by_another(dir: &Path) -> Option<String> {
    let path = dir.join(LOCK_FILE);
    let mut f = File::open(&path).ok()?;
    let mut holder = String::new();
    {
        use std::io::Read;
        let _ = f.read_to_string(&mut holder);
    }
    let holder = holder.trim();
    if holder == std::process::id().to_string() {
        return None;
    }
    #[cfg(unix)]
    {
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a file descriptor this function owns; closing it (the drop at
        // return) releases a lock taken here.
        let rc = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_SH | libc::LOCK_NB) };
        if rc != 0 {
            return Some(format!(
                "another stickslip process{} is writing into the folder {}; wait for it or \
                 choose another folder",
                holder_pid(holder),
                dir.display()
            ));
        }
    }
    None
}

/// Ok when `dir` is an existing folder in which a new file can be created (tried).
fn probe_folder(dir: &Path) -> Result<(), String> {
    let shown = dir.display();
    match std::fs::metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(format!("the folder {shown} does not exist"))
        }
        Err(e) => return Err(format!("cannot use the folder {shown}: {e}")),
        Ok(m) if !m.is_dir() => return Err(format!("{shown} is not a folder")),
        Ok(_) => {}
    }
    let probe = temp_name(dir, "write-probe");
    match OpenOptions::new().write(true).create_new(true).open(&probe) {
        Ok(f) => {
            drop(f);
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) => Err(format!("cannot create files in the folder {shown}: {e}")),
    }
}

/// A fresh temporary path beside `name` in `dir`.
fn temp_name(dir: &Path, name: &str) -> PathBuf {
    static COUNT: AtomicU64 = AtomicU64::new(0);
    dir.join(format!(
        ".{name}{TMP_MARK}{}-{}",
        std::process::id(),
        COUNT.fetch_add(1, Ordering::Relaxed)
    ))
}

/// Writes a result file atomically: `fill` writes to a temporary file in the same folder,
/// which is then renamed onto `path` (links in `path` resolved first, so a link keeps
/// pointing at the new file). On any error the temporary file is removed and `path` is
/// left as it was. A device or a pipe at `path` is written in place.
pub fn write_atomic(
    path: impl AsRef<Path>,
    fill: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let target = resolve_links(path.as_ref())?;
    if std::fs::metadata(&target).is_ok_and(|m| m.is_file() && m.permissions().readonly()) {
        return Err(std::io::Error::new(
            std::io::ErrorKind::PermissionDenied,
            "the file is read-only",
        ));
    }
    if std::fs::metadata(&target).is_ok_and(|m| !m.is_file() && !m.is_dir()) {
        let mut w = BufWriter::new(OpenOptions::new().write(true).open(&target)?);
        fill(&mut w)?;
        return w.flush();
    }
    let name = target
        .file_name()
        .ok_or_else(|| std::io::Error::other("the path names no file"))?
        .to_string_lossy()
        .into_owned();
    let tmp = temp_name(&parent_of(&target), &name);
    let result = (|| {
        let f = OpenOptions::new().write(true).create_new(true).open(&tmp)?;
        let mut w = BufWriter::with_capacity(1 << 20, f);
        fill(&mut w)?;
        w.flush()?;
        drop(w);
        std::fs::rename(&tmp, &target)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// [`write_atomic`] of bytes already in memory.
pub fn write_atomic_bytes(path: impl AsRef<Path>, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic(path, |w| w.write_all(bytes))
}

/// Does `name` (one path component) match `pattern` (at most one `*`, which matches any
/// run of characters)?
fn glob_match(pattern: &str, name: &str) -> bool {
    match pattern.split_once('*') {
        None => pattern == name,
        Some((pre, post)) => {
            name.len() >= pre.len() + post.len() && name.starts_with(pre) && name.ends_with(post)
        }
    }
}

/// A relative path of plain components (no `..`, no root): what a manifest may name.
fn is_inside(rel: &Path) -> bool {
    !rel.as_os_str().is_empty() && rel.components().all(|c| matches!(c, Component::Normal(_)))
}

/// An output folder owned by one command for one run: locked against a concurrent run,
/// cleared of what the previous run of the same command wrote, with a manifest of what
/// this run writes. Created by [`OutputDir::open`]; [`OutputDir::clean`] before the
/// first write; [`OutputDir::write`] for each result file.
pub struct OutputDir {
    dir: PathBuf,
    command: String,
    /// The command's output names, relative, `*` allowed in the last component.
    patterns: Vec<String>,
    /// Stale files with the command's output names that no manifest lists.
    strays: Vec<PathBuf>,
    /// What the previous run's manifest lists (relative paths).
    previous: Vec<PathBuf>,
    inputs: InputIds,
    manifest: Option<File>,
    recorded: std::collections::HashSet<PathBuf>,
    /// Held for the run: the kernel releases the lock when the process ends.
    _lock: File,
}

impl OutputDir {
    /// Checks, without creating or changing anything, that `dir` could be taken for
    /// `command` by [`OutputDir::open`]: it is a folder (or can be created: its nearest
    /// existing ancestor is a writable folder), files can be created in it, and (when it
    /// exists) it holds no stray files with the command's output names (unless
    /// `overwrite`) and no input among the files a run would remove or replace.
    pub fn check(
        dir: &Path,
        option: &str,
        command: &str,
        patterns: &[&str],
        inputs: &[Named],
        overwrite: bool,
    ) -> Result<(), InputError> {
        let shown = dir.display().to_string();
        let fail = |problem: String| InputError::new(&shown, option, problem);
        match std::fs::metadata(dir) {
            Ok(m) if !m.is_dir() => Err(fail("is a file, not a folder".into())),
            Ok(_) => {
                probe_folder(dir).map_err(&fail)?;
                Survey::take(dir, command, patterns, &InputIds::new(inputs), overwrite)
                    .map(|_| ())
                    .map_err(fail)
            }
            Err(_) => {
                // The folder will be created: its nearest existing ancestor must accept it.
                let mut up = dir.to_path_buf();
                loop {
                    up = parent_of(&up);
                    match std::fs::metadata(&up) {
                        Ok(m) if m.is_dir() => return probe_folder(&up).map_err(&fail),
                        Ok(_) => {
                            return Err(fail(format!(
                                "cannot be created: {} is a file",
                                up.display()
                            )))
                        }
                        Err(_) if up.parent().is_none() || up == Path::new(".") => {
                            return Err(fail("cannot be created".into()))
                        }
                        Err(_) => {}
                    }
                }
            }
        }
    }

    /// Takes `dir` for `command` (creating it): checks it can be written, takes the lock,
    /// reads the previous manifest, and refuses (unless `overwrite`) when it holds files
    /// named like the command's outputs (`patterns`) that no manifest of the command lists,
    /// or when one of `inputs` would be removed or overwritten. Nothing is removed here.
    pub fn open(
        dir: &Path,
        option: &str,
        command: &str,
        patterns: &[&str],
        inputs: &[Named],
        overwrite: bool,
    ) -> Result<OutputDir, InputError> {
        let shown = dir.display().to_string();
        let fail = |problem: String| InputError::new(&shown, option, problem);
        if std::fs::metadata(dir).is_ok_and(|m| !m.is_dir()) {
            return Err(fail("is a file, not a folder".into()));
        }
        std::fs::create_dir_all(dir).map_err(|e| fail(format!("cannot create the folder: {e}")))?;
        probe_folder(dir).map_err(&fail)?;
        let lock = take_lock(dir).map_err(&fail)?;
        let ids = InputIds::new(inputs);
        let survey = Survey::take(dir, command, patterns, &ids, overwrite).map_err(fail)?;
        Ok(OutputDir {
            dir: dir.to_path_buf(),
            command: command.to_string(),
            patterns: patterns.iter().map(|s| s.to_string()).collect(),
            strays: survey.strays,
            previous: survey.previous,
            inputs: ids,
            manifest: None,
            recorded: Default::default(),
            _lock: lock,
        })
    }

    /// The folder.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Removes what the previous run of this command wrote here (its manifest), the stray
    /// files `open` found (only reached with `overwrite`) and the temporary files a killed
    /// run left, then starts this run's manifest.
    pub fn clean(&mut self) -> std::io::Result<()> {
        for rel in self.previous.iter().chain(&self.strays) {
            let p = self.dir.join(rel);
            // Only plain files (never a folder, never through a link) and never an input.
            let plain = std::fs::symlink_metadata(&p).is_ok_and(|m| m.is_file());
            if plain && self.inputs.same_as(&p).is_none() {
                std::fs::remove_file(&p)?;
            }
        }
        self.remove_temporaries();
        let mpath = self.dir.join(manifest_name(&self.command));
        let mut m = File::create(&mpath)?;
        writeln!(
            m,
            "# files `stickslip {}` wrote in this folder; its next run here removes them",
            self.command
        )?;
        self.manifest = Some(m);
        self.previous.clear();
        self.strays.clear();
        Ok(())
    }

    /// Removes the temporary files of atomic writes ([`write_atomic`]) that a killed run
    /// left beside the command's output names (best effort: one that cannot be removed
    /// stays, and is removed next time).
    pub fn remove_temporaries(&self) {
        for pat in &self.patterns {
            let (sub, _) = split_pattern(pat);
            let folder = self.dir.join(sub);
            let Ok(entries) = std::fs::read_dir(&folder) else {
                continue;
            };
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                if let Some((base, _)) = name.strip_prefix('.').and_then(|n| n.split_once(TMP_MARK))
                {
                    let (_, file_pat) = split_pattern(pat);
                    if glob_match(file_pat, base) && e.file_type().is_ok_and(|t| t.is_file()) {
                        let _ = std::fs::remove_file(e.path());
                    }
                }
            }
        }
    }

    /// Continues the previous run's manifest instead of [`OutputDir::clean`] (a resumed
    /// run): nothing is removed, what it lists stays this run's, and new names are added.
    pub fn resume(&mut self) -> std::io::Result<()> {
        let mpath = self.dir.join(manifest_name(&self.command));
        let m = OpenOptions::new().append(true).open(&mpath)?;
        self.recorded.extend(self.previous.drain(..));
        self.strays.clear();
        self.manifest = Some(m);
        Ok(())
    }

    /// Records `rel` in the manifest (before the file exists, so a killed run's files are
    /// still cleaned up next time) and returns its full path.
    pub fn record(&mut self, rel: impl AsRef<Path>) -> std::io::Result<PathBuf> {
        let rel = rel.as_ref();
        if self.recorded.insert(rel.to_path_buf()) {
            if let Some(m) = self.manifest.as_mut() {
                // One write per line: a killed process leaves whole lines.
                m.write_all(format!("{}\n", rel.display()).as_bytes())?;
            }
        }
        Ok(self.dir.join(rel))
    }

    /// Writes the result file `rel` atomically ([`write_atomic`]) and records it.
    pub fn write(
        &mut self,
        rel: impl AsRef<Path>,
        fill: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
    ) -> std::io::Result<PathBuf> {
        let p = self.record(rel)?;
        write_atomic(&p, fill)?;
        Ok(p)
    }
}

/// What an existing output folder holds for one command: the previous run's files (its
/// manifest) and stray files with the command's output names that no manifest lists.
struct Survey {
    previous: Vec<PathBuf>,
    strays: Vec<PathBuf>,
}

impl Survey {
    /// Looks at `dir`; the error (a problem for an [`InputError`]) refuses the folder.
    fn take(
        dir: &Path,
        command: &str,
        patterns: &[&str],
        ids: &InputIds,
        overwrite: bool,
    ) -> Result<Survey, String> {
        let previous: Vec<PathBuf> = std::fs::read_to_string(dir.join(manifest_name(command)))
            .unwrap_or_default()
            .lines()
            .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
            .map(PathBuf::from)
            .filter(|p| is_inside(p))
            .collect();
        let mut strays = Vec::new();
        let mut existing = Vec::new();
        for pat in patterns {
            for rel in matching(dir, pat) {
                if !previous.contains(&rel) {
                    strays.push(rel.clone());
                }
                existing.push(rel);
            }
        }
        // Every file this run would remove or replace must not be an input.
        for rel in previous.iter().chain(&existing) {
            if let Some(input) = ids.same_as(&dir.join(rel)) {
                return Err(format!(
                    "holds {}, which is the input {input}: the run would remove or replace it; \
                     choose another folder",
                    rel.display()
                ));
            }
        }
        if !strays.is_empty() && !overwrite {
            let names: Vec<String> = strays
                .iter()
                .take(3)
                .map(|p| p.display().to_string())
                .collect();
            let more = if strays.len() > 3 {
                format!(" and {} more", strays.len() - 3)
            } else {
                String::new()
            };
            return Err(format!(
                "already holds {}{more}, not written by a previous `stickslip {command}` there; \
                 pass --overwrite to replace such files, or choose another folder",
                names.join(", ")
            ));
        }
        Ok(Survey { previous, strays })
    }
}

fn manifest_name(command: &str) -> String {
    format!(".stickslip-{command}.manifest")
}

/// (sub-folder, file pattern) of a relative pattern such as `frames/*.vtk`.
fn split_pattern(pat: &str) -> (&str, &str) {
    match pat.rsplit_once('/') {
        Some((d, f)) => (d, f),
        None => ("", pat),
    }
}

/// The files (relative paths) in `dir` that match `pat`; dot files never match.
fn matching(dir: &Path, pat: &str) -> Vec<PathBuf> {
    let (sub, file_pat) = split_pattern(pat);
    let Ok(entries) = std::fs::read_dir(dir.join(sub)) else {
        return Vec::new();
    };
    let mut out: Vec<PathBuf> = entries
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            (!name.starts_with('.') && glob_match(file_pat, &name))
                .then(|| Path::new(sub).join(name))
        })
        .collect();
    out.sort();
    out
}

/// " (pid N)" from a lock file's content, or nothing when it is empty.
fn holder_pid(holder: &str) -> String {
    if holder.is_empty() {
        String::new()
    } else {
        format!(" (pid {})", crate::io::one_line(holder, 20))
    }
}

/// Takes the folder's lock without waiting; the error says who holds it.
fn take_lock(dir: &Path) -> Result<File, String> {
    let path = dir.join(LOCK_FILE);
    let mut f = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|e| format!("cannot create the lock file {LOCK_FILE}: {e}"))?;
    #[cfg(unix)]
    {
        use std::io::Read;
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a file descriptor this function owns; no memory is shared.
        let rc = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if rc != 0 {
            let mut holder = String::new();
            let _ = f.read_to_string(&mut holder);
            return Err(format!(
                "another stickslip process{} is writing into this folder; wait for it or \
                 choose another folder",
                holder_pid(holder.trim())
            ));
        }
        let _ = f.set_len(0);
        let _ = f.write_all(format!("{}\n", std::process::id()).as_bytes());
    }
    Ok(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("stickslip-files-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn glob() {
        assert!(glob_match("*.vtk", "a_00001.vtk"));
        assert!(!glob_match("*.vtk", "a.vtu"));
        assert!(glob_match("H.mtx", "H.mtx"));
        assert!(!glob_match("ab*ba", "aba"));
    }

    #[test]
    fn same_file_through_links_is_refused() {
        let d = tmp("links");
        let input = d.join("g.mtx");
        std::fs::write(&input, "x").unwrap();
        let hard = d.join("hard.mtx");
        std::fs::hard_link(&input, &hard).unwrap();
        let inputs = [Named::new("--gradient", &input)];
        for out in [&input, &hard] {
            let e = check_outputs(&inputs, &[Named::new("--out", out)]).unwrap_err();
            assert!(e.problem.contains("the input --gradient"), "{e}");
        }
        #[cfg(unix)]
        {
            let soft = d.join("soft.mtx");
            std::os::unix::fs::symlink("g.mtx", &soft).unwrap();
            let e = check_outputs(&inputs, &[Named::new("--out", &soft)]).unwrap_err();
            assert!(e.problem.contains("the input"), "{e}");
        }
        let a = d.join("a.mtx");
        let e = check_outputs(
            &inputs,
            &[Named::new("--out", &a), Named::new("--reactions", &a)],
        )
        .unwrap_err();
        assert!(e.problem.contains("the output --out"), "{e}");
        let e = check_outputs(&inputs, &[Named::new("--out", &d.join("no/dx.mtx"))]).unwrap_err();
        assert!(e.problem.contains("does not exist"), "{e}");
        assert!(check_outputs(&inputs, &[Named::new("--out", &a)]).is_ok());
        // A read-only file stays (a rename would replace it even where writing is denied).
        let ro = d.join("ro.mtx");
        std::fs::write(&ro, "keep").unwrap();
        let mut perm = std::fs::metadata(&ro).unwrap().permissions();
        perm.set_readonly(true);
        std::fs::set_permissions(&ro, perm).unwrap();
        let e = check_outputs(&inputs, &[Named::new("--out", &ro)]).unwrap_err();
        assert!(e.problem.contains("read-only"), "{e}");
        assert!(write_atomic_bytes(&ro, b"new").is_err());
        assert_eq!(std::fs::read_to_string(&ro).unwrap(), "keep");
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn atomic_write_keeps_the_old_file_on_error() {
        let d = tmp("atomic");
        let p = d.join("f.mtx");
        std::fs::write(&p, "old").unwrap();
        let e = write_atomic(&p, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("stop"))
        });
        assert!(e.is_err());
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "old");
        write_atomic_bytes(&p, b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "new");
        // Nothing but the file itself is left in the folder.
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 1);
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn owned_folder_removes_only_its_own_files() {
        let d = tmp("owned");
        let mine = ["a.txt", "sub/*.vtk"];
        let mut o = OutputDir::open(&d, "--out", "test", &mine, &[], false).unwrap();
        o.clean().unwrap();
        std::fs::create_dir_all(d.join("sub")).unwrap();
        for k in 0..5 {
            o.write(format!("sub/f{k}.vtk"), |w| w.write_all(b"v"))
                .unwrap();
        }
        o.write("a.txt", |w| w.write_all(b"a")).unwrap();
        std::fs::write(d.join("notes.txt"), "user").unwrap();
        // A second run while the first holds the folder refuses.
        let e = OutputDir::open(&d, "--out", "test", &mine, &[], false)
            .err()
            .unwrap();
        assert!(e.problem.contains("another stickslip process"), "{e}");
        drop(o);
        let mut o = OutputDir::open(&d, "--out", "test", &mine, &[], false).unwrap();
        o.clean().unwrap();
        o.write("sub/f0.vtk", |w| w.write_all(b"v")).unwrap();
        drop(o);
        assert!(d.join("sub/f0.vtk").exists());
        assert!(!d.join("sub/f1.vtk").exists());
        assert!(!d.join("a.txt").exists());
        assert!(d.join("notes.txt").exists());
        // A stray file with an output name is refused without overwrite.
        std::fs::write(d.join("sub/g.vtk"), "x").unwrap();
        let e = OutputDir::open(&d, "--out", "test", &mine, &[], false)
            .err()
            .unwrap();
        assert!(e.problem.contains("sub/g.vtk"), "{e}");
        let mut o = OutputDir::open(&d, "--out", "test", &mine, &[], true).unwrap();
        o.clean().unwrap();
        assert!(!d.join("sub/g.vtk").exists());
        std::fs::remove_dir_all(&d).ok();
    }
}
