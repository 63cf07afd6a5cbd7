//! Files that are either whole or absent, and one writer per output folder.
//!
//! - [`write_atomically`]: the content goes to a hidden temporary file beside the target, is
//!   flushed to disk, and is renamed over the target (a rename within a folder is atomic on
//!   POSIX file systems). A run killed while writing leaves the previous file intact, never a
//!   truncated or empty one, and a reader never sees half of a file.
//! - [`FolderLock`]: an exclusive advisory lock on `FOLDER/.lock` held while a run writes into
//!   the folder. The operating system releases it when the process ends, however it ends, so a
//!   killed run never leaves a stale lock behind.

use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Name of the lock file inside a locked folder.
pub const LOCK_FILE: &str = ".lock";

/// Distinguishes temporary files of one process (several threads may write at once).
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// The hidden temporary sibling `target` is written to before the rename. It keeps the
/// target's extension: some writers choose the format by it.
fn temporary_path(target: &Path) -> PathBuf {
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".into());
    let extension = target
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    target.with_file_name(format!(".{name}.tmp-{}-{n}{extension}", std::process::id()))
}

/// Lets `write` write a temporary sibling of `target` (the path it is given), then flushes it
/// to disk and renames it over `target`. On any error the temporary file is removed and
/// `target` is untouched; `io_error` turns the flush or rename's error into the caller's.
pub fn write_via_temporary<E>(
    target: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_error: impl FnOnce(io::Error) -> E,
) -> Result<(), E> {
    let temporary = temporary_path(target);
    let result = write(&temporary).and_then(|()| {
        File::open(&temporary)
            .and_then(|f| f.sync_all())
            .and_then(|()| fs::rename(&temporary, target))
            .map_err(io_error)
    });
    if result.is_err() {
        let _ = fs::remove_file(&temporary);
    }
    result
}

/// Writes `target` through `write` into a temporary sibling, then renames it into place (see
/// [`write_via_temporary`]).
pub fn write_atomically<F>(target: &Path, write: F) -> io::Result<()>
where
    F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
{
    write_via_temporary(
        target,
        |temporary| {
            let mut out = BufWriter::new(File::create(temporary)?);
            write(&mut out)?;
            out.flush()
        },
        |e| e,
    )
}

/// [`write_atomically`] of a byte buffer: a drop-in for `std::fs::write` that never leaves a
/// truncated file.
pub fn write_bytes_atomically(target: impl AsRef<Path>, bytes: impl AsRef<[u8]>) -> io::Result<()> {
    write_atomically(target.as_ref(), |out| out.write_all(bytes.as_ref()))
}

/// Errors taking a folder's lock.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LockError {
    /// The lock file could not be created or locked.
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: io::Error },
    /// Another process holds the lock.
    #[error(
        "{folder} is in use by another mlsss run{holder}: wait for it to finish, or choose \
         another --out"
    )]
    Busy { folder: PathBuf, holder: String },
}

/// An exclusive lock on a folder, held until dropped (or the process ends).
#[derive(Debug)]
pub struct FolderLock {
    file: File,
}

impl FolderLock {
    /// Takes the lock of `folder` (created if missing) without waiting: [`LockError::Busy`]
    /// when another process (or another lock in this one) holds it.
    pub fn acquire(folder: &Path) -> Result<Self, LockError> {
        let path = folder.join(LOCK_FILE);
        let io = |source| LockError::Io {
            path: path.clone(),
            source,
        };
        fs::create_dir_all(folder).map_err(io)?;
        let mut file = fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&path)
            .map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(fs::TryLockError::WouldBlock) => {
                let holder = fs::read_to_string(&path)
                    .ok()
                    .map(|pid| pid.trim().to_owned())
                    .filter(|pid| !pid.is_empty())
                    .map(|pid| format!(" (process {pid})"))
                    .unwrap_or_default();
                return Err(LockError::Busy {
                    folder: folder.to_owned(),
                    holder,
                });
            }
            Err(fs::TryLockError::Error(e)) => return Err(io(e)),
        }
        // Who holds it, for the message another run prints (the lock is what counts).
        file.set_len(0).map_err(io)?;
        write!(file, "{}", std::process::id()).map_err(io)?;
        Ok(Self { file })
    }
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        let _ = self.file.set_len(0);
        let _ = self.file.unlock();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_write_keeps_the_previous_file_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("model.bin");
        write_bytes_atomically(&target, b"good").unwrap();
        let err = write_atomically(&target, |out| {
            out.write_all(b"half of a new")?;
            Err(io::Error::other("killed while saving"))
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "killed while saving");
        assert_eq!(fs::read(&target).unwrap(), b"good");
        let names: Vec<_> = fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["model.bin"]);
    }

    #[test]
    fn a_second_lock_on_a_folder_is_refused_until_the_first_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let first = FolderLock::acquire(dir.path()).unwrap();
        let err = FolderLock::acquire(dir.path()).unwrap_err();
        assert!(matches!(err, LockError::Busy { .. }), "{err}");
        assert!(
            err.to_string()
                .contains(&format!("process {}", std::process::id())),
            "{err}"
        );
        drop(first);
        FolderLock::acquire(dir.path()).unwrap();
    }
}
