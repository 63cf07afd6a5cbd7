//! Finding controllers: serial ports (serialport's enumeration, which on Linux reads
//! `/sys/class/tty`) and USB devices (read from `/sys/bus/usb/devices`, so no libusb is needed).
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
    fn a_missing_sysfs_root_is_no_devices() {
        assert!(usb_devices(Path::new("/nonexistent/usb")).is_empty());
    }

    #[test]
    fn product_string_naming_the_project_is_a_controller() {
        assert!(controller_reason(0x1209, 0x0001, Some("MLSSS booth controller")).is_some());
        assert!(controller_reason(0x1209, 0x0001, Some("keyboard")).is_none());
    }
}
