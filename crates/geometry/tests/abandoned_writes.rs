//! `write_atomic_with` against a signal handler's `abandon_pending_writes` (its own test binary:
//! the pending-writes lock is process-wide).

use std::path::Path;
use std::time::Duration;

fn temporaries(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".tmp"))
        .collect()
}

/// A handler that abandoned the pending writes holds their lock until the process exits; a
/// write that starts meanwhile must not create its temporary file, which no one would remove
/// (it used to create it first and record it after, leaving it behind when the signal fell
/// between the two).
#[test]
fn no_temporary_file_is_created_while_the_pending_writes_are_abandoned() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pose.json");
    let guard = ic_geometry::io::abandon_pending_writes();
    let writer = {
        let path = path.clone();
        std::thread::spawn(move || {
            ic_geometry::io::write_atomic_with(
                &path,
                |w| std::io::Write::write_all(w, b"{}"),
                |e| e,
            )
        })
    };
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(temporaries(dir.path()), Vec::<String>::new());
    assert!(!path.exists());
    assert!(!writer.is_finished(), "the write went on under the guard");
    // In a test the guard can be dropped (a handler exits holding it): the write then completes.
    drop(guard);
    writer.join().unwrap().unwrap();
    assert_eq!(std::fs::read(&path).unwrap(), b"{}");
    assert_eq!(temporaries(dir.path()), Vec::<String>::new());
}
