//! Finding controllers: serial ports (serialport's enumeration, which on Linux reads
//! `/sys/class/tty`) and USB devices through libusb (`rusb`), falling back to
//! `/sys/bus/usb/devices` where libusb cannot run (no usbfs in a container).
//! A device "looks like a controller" when its USB ids are those of a supported board's
//! debugger/USB-serial bridge or its product string names the project.

use std::path::Path;

use serde::Serialize;

/// USB ids of boards the firmware supports: (vendor, product, what it is).
pub const CONTROLLER_USB_IDS: &[(u16, u16, &str)] = &[
    (0x0483, 0x374b, "ST-LINK/V2-1 (STM32 Nucleo)"),
    (0x0483, 0x374e, "STLINK-V3 (STM32 Nucleo)"),
    (0x0483, 0x3752, "ST-LINK/V2-1 (STM32 Nucleo)"),
    (0x0483, 0x3753, "STLINK-V3 (STM32 Nucleo)"),
    (0x0483, 0x5740, "STM32 virtual COM port"),
];

/// A serial port.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct SerialCandidate {
    /// Device path.
    pub path: String,
    /// USB vendor id, if the port is on USB.
    pub vid: Option<u16>,
    /// USB product id.
    pub pid: Option<u16>,
    /// USB product string.
    pub product: Option<String>,
    /// Why it looks like a controller, if it does.
    pub controller: Option<String>,
}

/// A USB device.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct UsbCandidate {
    /// Bus path (e.g. `1-1.2`).
    pub bus_path: String,
    /// Vendor id.
    pub vid: u16,
    /// Product id.
    pub pid: u16,
    /// Product string.
    pub product: Option<String>,
    /// Why it looks like a controller, if it does.
    pub controller: Option<String>,
}

/// Why a device with these ids / product string looks like a controller.
pub fn controller_reason(vid: u16, pid: u16, product: Option<&str>) -> Option<String> {
    if let Some((_, _, what)) = CONTROLLER_USB_IDS
        .iter()
        .find(|(v, p, _)| *v == vid && *p == pid)
    {
        return Some((*what).to_owned());
    }
    product
        .filter(|p| p.to_ascii_lowercase().contains("mlsss"))
        .map(|p| format!("product string \"{p}\""))
}

/// Every serial port the OS lists.
pub fn serial_ports() -> Result<Vec<SerialCandidate>, serialport::Error> {
    let ports = serialport::available_ports()?;
    Ok(ports
        .into_iter()
        .map(|info| match info.port_type {
            serialport::SerialPortType::UsbPort(usb) => SerialCandidate {
                controller: controller_reason(usb.vid, usb.pid, usb.product.as_deref()),
                path: info.port_name,
                vid: Some(usb.vid),
                pid: Some(usb.pid),
                product: usb.product,
            },
            _ => SerialCandidate {
                path: info.port_name,
                vid: None,
                pid: None,
                product: None,
                controller: None,
            },
        })
        .collect())
}

/// Whether libusb can start here (it cannot without usbfs, e.g. in a container with no USB);
/// the error says why not. Probe this before any library that uses rusb's global context,
/// which panics instead of returning the error.
pub fn libusb_available() -> Result<(), rusb::Error> {
    rusb::Context::new().map(|_| ())
}

/// Where a USB device list came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum UsbSource {
    /// libusb's device list.
    Libusb,
    /// `/sys/bus/usb/devices` (libusb could not be initialised).
    Sysfs,
}

/// Every USB device libusb lists, or, when libusb cannot start, those under `sysfs_root`.
pub fn usb_devices_any(sysfs_root: &Path) -> (Vec<UsbCandidate>, UsbSource) {
    match usb_devices_libusb() {
        Ok(devices) => (devices, UsbSource::Libusb),
        Err(_) => (usb_devices(sysfs_root), UsbSource::Sysfs),
    }
}

/// Every USB device libusb lists, named by bus path (`1-1.2`, as in sysfs). The product string
/// needs the device opened, which may be refused (permissions): then it is `None`.
pub fn usb_devices_libusb() -> Result<Vec<UsbCandidate>, rusb::Error> {
    // An own context, not rusb's global one, which panics where libusb cannot start.
    let context = rusb::Context::new()?;
    let mut out: Vec<UsbCandidate> = rusb::UsbContext::devices(&context)?
        .iter()
        .filter_map(|device| {
            let descriptor = device.device_descriptor().ok()?;
            let product = device
                .open()
                .ok()
                .and_then(|handle| handle.read_product_string_ascii(&descriptor).ok());
            let (vid, pid) = (descriptor.vendor_id(), descriptor.product_id());
            Some(UsbCandidate {
                bus_path: bus_path(
                    device.bus_number(),
                    &device.port_numbers().unwrap_or_default(),
                ),
                vid,
                pid,
                controller: controller_reason(vid, pid, product.as_deref()),
                product,
            })
        })
        .collect();
    out.sort_by(|a, b| a.bus_path.cmp(&b.bus_path));
    Ok(out)
}

/// The kernel's name for a device: `usb<bus>` for a root hub, else `<bus>-<port>.<port>...`.
fn bus_path(bus: u8, ports: &[u8]) -> String {
    if ports.is_empty() {
        return format!("usb{bus}");
    }
    let ports: Vec<String> = ports.iter().map(u8::to_string).collect();
    format!("{bus}-{}", ports.join("."))
}

/// Every USB device under `root` (normally `/sys/bus/usb/devices`); interfaces and unreadable
/// entries are skipped. A missing root (no USB, a container) is an empty list.
pub fn usb_devices(root: &Path) -> Vec<UsbCandidate> {
    let Ok(entries) = std::fs::read_dir(root) else {
        return vec![];
    };
    let mut out: Vec<UsbCandidate> = entries
        .flatten()
        .filter_map(|entry| {
            let dir = entry.path();
            let vid = read_hex_id(&dir.join("idVendor"))?;
            let pid = read_hex_id(&dir.join("idProduct"))?;
            let product = std::fs::read_to_string(dir.join("product"))
                .ok()
                .map(|s| s.trim().to_owned());
            Some(UsbCandidate {
                bus_path: entry.file_name().to_string_lossy().into_owned(),
                vid,
                pid,
                controller: controller_reason(vid, pid, product.as_deref()),
                product,
            })
        })
        .collect();
    out.sort_by(|a, b| a.bus_path.cmp(&b.bus_path));
    out
}

fn read_hex_id(path: &Path) -> Option<u16> {
    let text = std::fs::read_to_string(path).ok()?;
    u16::from_str_radix(text.trim(), 16).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn usb_devices_are_read_from_sysfs_layout() {
        let root = tempfile::tempdir().unwrap();
        let nucleo = root.path().join("1-1.2");
        std::fs::create_dir(&nucleo).unwrap();
        std::fs::write(nucleo.join("idVendor"), "0483\n").unwrap();
        std::fs::write(nucleo.join("idProduct"), "374b\n").unwrap();
        std::fs::write(nucleo.join("product"), "STM32 STLink\n").unwrap();
        let mouse = root.path().join("1-1.3");
        std::fs::create_dir(&mouse).unwrap();
        std::fs::write(mouse.join("idVendor"), "046d\n").unwrap();
        std::fs::write(mouse.join("idProduct"), "c077\n").unwrap();
        // An interface directory has no ids and is skipped.
        std::fs::create_dir(root.path().join("1-1.2:1.0")).unwrap();

        let found = usb_devices(root.path());
        assert_eq!(found.len(), 2);
        assert_eq!((found[0].vid, found[0].pid), (0x0483, 0x374b));
        assert!(found[0].controller.is_some());
        assert_eq!(found[1].controller, None);
    }

    #[test]
    fn bus_paths_follow_the_kernels_naming() {
        assert_eq!(bus_path(1, &[]), "usb1");
        assert_eq!(bus_path(1, &[1]), "1-1");
        assert_eq!(bus_path(3, &[1, 4, 2]), "3-1.4.2");
    }

    #[test]
    fn libusb_and_sysfs_list_the_same_devices() {
        // Where libusb runs, it must see every device the kernel lists (same ids, same bus
        // paths); where it cannot (no usbfs), the sysfs fallback is what `rig ports` shows.
        let sysfs = usb_devices(Path::new("/sys/bus/usb/devices"));
        let (listed, source) = usb_devices_any(Path::new("/sys/bus/usb/devices"));
        match source {
            UsbSource::Sysfs => assert_eq!(listed, sysfs),
            UsbSource::Libusb => {
                let ids = |v: &[UsbCandidate]| {
                    let mut ids: Vec<_> = v
                        .iter()
                        .map(|d| (d.bus_path.clone(), d.vid, d.pid))
                        .collect();
                    ids.sort();
                    ids
                };
                assert_eq!(ids(&listed), ids(&sysfs));
            }
        }
    }

    #[test]
    fn a_missing_sysfs_root_is_no_devices() {
        assert!(usb_devices(Path::new("/nonexistent/usb")).is_empty());
    }

    #[test]
    fn product_string_naming_the_project_is_a_controller() {
        assert!(controller_reason(0x1209, 0x0001, Some("MLSSS booth controller")).is_some());
        assert!(controller_reason(0x1209, 0x0001, Some("keyboard")).is_none());
    }
}
