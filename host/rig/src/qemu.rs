//! The emulated controller: the real firmware image under `qemu-system-arm -machine mps2-an386`
//! with deterministic virtual time (`-icount shift=N,sleep=off`), its UART0 wired to a
//! pseudo-terminal that the host opens with `serialport`. QEMU is killed when the guard drops,
//! on success, error or panic alike.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use serialport::{SerialPort, TTYPort};

use super::RigError;

/// Firmware image built by the README's test command, relative to the workspace root.
pub const FIRMWARE_IMAGE: &str = "firmware/target/thumbv7em-none-eabihf/release/mlsss-fw-qemu";
/// The command that builds [`FIRMWARE_IMAGE`].
pub const FIRMWARE_BUILD_COMMAND: &str = "cd firmware && cargo build --release -p mlsss-fw-qemu";
/// Default `-icount` shift: 2^4 ns of virtual time per guest instruction.
pub const DEFAULT_ICOUNT_SHIFT: u8 = 4;
const QEMU: &str = "qemu-system-arm";

/// The default firmware image: next to the current directory if it is the workspace, else in the
/// workspace this binary was built from.
pub fn default_firmware_image() -> PathBuf {
    let local = PathBuf::from(FIRMWARE_IMAGE);
    if local.exists() {
        return local;
    }
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(FIRMWARE_IMAGE)
}

/// A running QEMU; killed on drop.
pub struct QemuGuard {
    child: Child,
    /// The pty's slave side stays open so the pty survives until QEMU has it.
    _slave: TTYPort,
}

impl Drop for QemuGuard {
    fn drop(&mut self) {
        // Kill errors mean it has exited already; wait reaps it either way.
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl QemuGuard {
    /// Whether QEMU is still running (it exits on a guest fault or a bad command line).
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }
}

/// Boots `image` under QEMU; returns the guard and the host end of the controller's UART0.
pub fn spawn(image: &Path, icount_shift: u8) -> Result<(QemuGuard, Box<dyn SerialPort>), RigError> {
    if !image.is_file() {
        return Err(RigError::FirmwareMissing {
            path: image.to_owned(),
            build: FIRMWARE_BUILD_COMMAND,
        });
    }
    let (master, slave) = TTYPort::pair().map_err(RigError::Serial)?;
    let slave_path = slave.name().ok_or(RigError::PtyName)?;
    let child = Command::new(QEMU)
        .args(["-machine", "mps2-an386", "-nographic", "-monitor", "none"])
        .args(["-icount", &format!("shift={icount_shift},sleep=off")])
        .args(["-serial", &slave_path])
        .arg("-kernel")
        .arg(image)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .map_err(|source| match source.kind() {
            std::io::ErrorKind::NotFound => RigError::QemuMissing,
            _ => RigError::QemuSpawn(source),
        })?;
    let guard = QemuGuard {
        child,
        _slave: slave,
    };
    Ok((guard, Box::new(master)))
}
