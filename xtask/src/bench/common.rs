//! Helpers every stage of `cargo xtask bench` shares: progress bars, workspace-relative paths
//! for the committed reports, atomic writes (and, in tests, a temporary folder). A leaf: it
//! uses no other module of the bench.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

/// A progress bar (a spinner when `len` is 0) labelled `what`.
pub fn progress_bar(len: u64, what: &str) -> ProgressBar {
    let bar = if len == 0 {
        ProgressBar::new_spinner()
    } else {
        ProgressBar::new(len)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{prefix:>16} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg} (eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_prefix(what.to_string());
    bar
}

/// `path` relative to the workspace root when it lies inside it (for reports that are
/// committed), else as given.
pub fn rel(path: &Path) -> PathBuf {
    let root = crate::workspace_root();
    let root = root.canonicalize().unwrap_or(root);
    path.strip_prefix(&root)
        .map(Path::to_path_buf)
        .unwrap_or_else(|_| path.to_path_buf())
}

/// Writes `bytes` to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    ic_geometry::io::create_parent_dir(path)
        .with_context(|| format!("creating {}", path.parent().unwrap_or(path).display()))?;
    ic_geometry::io::write_atomic_with(path, |w| std::io::Write::write_all(w, bytes), |e| e)
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
pub mod tests {
    use std::path::{Path, PathBuf};

    /// A temporary folder removed on drop (xtask has no tempfile).
    pub struct TempDir(PathBuf);

    impl TempDir {
        pub fn new(tag: &str) -> Self {
            use std::sync::atomic::{AtomicU64, Ordering};
            static N: AtomicU64 = AtomicU64::new(0);
            let p = std::env::temp_dir().join(format!(
                "xtask-{tag}-{}-{}",
                std::process::id(),
                N.fetch_add(1, Ordering::Relaxed)
            ));
            std::fs::create_dir_all(&p).unwrap();
            TempDir(p)
        }

        pub fn path(&self) -> &Path {
            &self.0
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}
