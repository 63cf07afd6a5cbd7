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

/// Name of the lock file inside a locked folder.
pub const LOCK_FILE: &str = ".lock";

/// A hidden, uniquely named temporary sibling of `target`, created empty. It keeps the target's
/// extension (some writers choose the format by it) and the permissions a plain `File::create`
/// would give (tempfile's default is owner-only, which would hide artefacts from other users).
fn temporary_sibling(target: &Path) -> io::Result<tempfile::NamedTempFile> {
    let folder = target
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".into());
    let extension = target
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    let prefix = format!(".{name}.tmp-");
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix).suffix(&extension);
    #[cfg(unix)]
    builder.permissions(<fs::Permissions as std::os::unix::fs::PermissionsExt>::from_mode(0o666));
    builder.tempfile_in(folder)
}

/// Lets `write` write a temporary sibling of `target` (the path it is given), then flushes it
/// to disk and renames it over `target`. On any error the temporary file is removed and
/// `target` is untouched; `io_error` turns the flush or rename's error into the caller's.
pub fn write_via_temporary<E>(
    target: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_error: impl FnOnce(io::Error) -> E,
) -> Result<(), E> {
    let temporary = match temporary_sibling(target) {
        Ok(t) => t,
        Err(e) => return Err(io_error(e)),
    };
    // On an error below, dropping `temporary` removes the file.
    write(temporary.path())?;
    File::open(temporary.path())
        .and_then(|f| f.sync_all())
        .and_then(|()| temporary.persist(target).map(drop).map_err(|e| e.error))
        .map_err(io_error)
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

    #[cfg(unix)]
    #[test]
    fn a_written_file_has_the_permissions_of_a_plain_create() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let (atomic, plain) = (dir.path().join("a.json"), dir.path().join("p.json"));
        write_bytes_atomically(&atomic, b"{}").unwrap();
        fs::write(&plain, b"{}").unwrap();
        let mode = |p: &Path| fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&atomic), mode(&plain));
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
