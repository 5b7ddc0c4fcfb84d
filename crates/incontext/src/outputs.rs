//! Checks on the paths a command writes, made before any work starts, so that nothing the user
//! already has is lost:
//! - an output may be a new path or an existing regular file, never a symbolic link, a device
//!   node (`/dev/null`, `/dev/full`), a FIFO, a socket or a folder (an atomic rename would put
//!   a file in its place);
//! - no output may be one of the command's input files, or another of its outputs (after
//!   resolving `.`/`..`, symbolic links in the folders, and hard links of existing files).
//!
//! Every refusal is bad input (exit code 2) and names the path and what it collides with.

use std::path::{Component, Path, PathBuf};

use crate::error::{CliError, Result};

/// A file the command reads (`what` names the flag, e.g. `--depth`).
#[derive(Clone, Copy, Debug)]
pub struct Named<'a> {
    pub what: &'a str,
    pub path: &'a Path,
}

impl<'a> Named<'a> {
    pub fn new(what: &'a str, path: &'a Path) -> Self {
        Named { what, path }
    }
}

/// The identity of a path: its absolute, normalised form with the longest existing ancestor
/// canonicalised (so `a/../b`, `./b` and a symlinked folder compare equal), and the (device,
/// inode) of the file when it exists (so hard links compare equal).
#[derive(Debug, PartialEq, Eq)]
struct Identity {
    path: PathBuf,
    inode: Option<(u64, u64)>,
}

impl Identity {
    fn of(path: &Path) -> Identity {
        let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
        let mut normal = PathBuf::new();
        for c in absolute.components() {
            match c {
                Component::ParentDir => {
                    normal.pop();
                }
                Component::CurDir => {}
                other => normal.push(other.as_os_str()),
            }
        }
        // Canonicalise the longest existing ancestor, keep the rest as written.
        let mut rest = Vec::new();
        let mut base = normal.clone();
        let resolved = loop {
            if let Ok(c) = base.canonicalize() {
                break c;
            }
            match (base.file_name().map(|n| n.to_os_string()), base.parent()) {
                (Some(name), Some(parent)) => {
                    rest.push(name);
                    base = parent.to_path_buf();
                }
                _ => break normal.clone(),
            }
        };
        let mut full = resolved;
        for name in rest.into_iter().rev() {
            full.push(name);
        }
        Identity {
            inode: inode(&full),
            path: full,
        }
    }

    fn same(&self, other: &Identity) -> bool {
        self.path == other.path || (self.inode.is_some() && self.inode == other.inode)
    }
}

#[cfg(unix)]
fn inode(path: &Path) -> Option<(u64, u64)> {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
}

#[cfg(not(unix))]
fn inode(_: &Path) -> Option<(u64, u64)> {
    None
}

/// Fails when `path` exists and is not a regular file (a symbolic link — even to a regular
/// file —, a device node, a FIFO, a socket or a folder): writing it would replace that thing.
pub fn check_replaceable(what: &str, path: &Path) -> Result<()> {
    let Ok(meta) = std::fs::symlink_metadata(path) else {
        return Ok(());
    };
    let ft = meta.file_type();
    if ft.is_file() {
        return Ok(());
    }
    let kind = ic_geometry::io::describe_file_type(&ft);
    Err(CliError::input(format!(
        "{}: refusing to write {what} there: it is {kind}, not a regular file \
         (give a new path or an existing regular file)",
        path.display()
    )))
}

/// Checks every output against [`check_replaceable`], against every input and against the
/// other outputs. Call it before any work starts.
pub fn check_outputs(inputs: &[Named], outputs: &[Named]) -> Result<()> {
    for o in outputs {
        check_replaceable(o.what, o.path)?;
    }
    let ins: Vec<(Named, Identity)> = inputs.iter().map(|n| (*n, Identity::of(n.path))).collect();
    let outs: Vec<(Named, Identity)> = outputs.iter().map(|n| (*n, Identity::of(n.path))).collect();
    for (i, (o, oid)) in outs.iter().enumerate() {
        if let Some((input, _)) = ins.iter().find(|(_, iid)| iid.same(oid)) {
            return Err(CliError::input(format!(
                "{}: {} would overwrite the {} input {}; choose another output path",
                o.path.display(),
                o.what,
                input.what,
                input.path.display()
            )));
        }
        if let Some((other, _)) = outs[..i].iter().find(|(_, id)| id.same(oid)) {
            return Err(CliError::input(format!(
                "{}: {} and {} name the same file; give each output its own path",
                o.path.display(),
                other.what,
                o.what
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identities_see_through_dots_parents_and_hard_links() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.json");
        std::fs::write(&a, b"{}").unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        let dotted = dir.path().join("sub").join("..").join(".").join("a.json");
        assert!(Identity::of(&a).same(&Identity::of(&dotted)));
        let link = dir.path().join("hard.json");
        std::fs::hard_link(&a, &link).unwrap();
        assert!(Identity::of(&a).same(&Identity::of(&link)));
        // Not yet existing paths compare by their normalised form.
        let new1 = dir.path().join("new").join("x.png");
        let new2 = dir.path().join("new").join("..").join("new").join("x.png");
        assert!(Identity::of(&new1).same(&Identity::of(&new2)));
        assert!(!Identity::of(&new1).same(&Identity::of(&a)));
    }
}
