//! The two ioctls the `v4l` crate cannot do without panicking on unusual drivers:
//! `VIDIOC_QUERYCAP` (its wrapper unwraps the card name as UTF-8, which a USB product string cut
//! at 32 bytes need not be) and `VIDIOC_QUERY_EXT_CTRL` for one control (its only wrapper
//! enumerates every control and unwraps their types and menu names).
#![allow(unsafe_code)]

use std::io;
use std::mem;
use std::os::raw::{c_int, c_void};

use v4l::v4l_sys::{
    V4L2_CAP_DEVICE_CAPS, V4L2_CTRL_FLAG_DISABLED, V4L2_CTRL_FLAG_READ_ONLY, v4l2_capability,
    v4l2_query_ext_ctrl,
};
use v4l::v4l2::{ioctl, vidioc};

/// What `VIDIOC_QUERYCAP` says about one device node.
#[derive(Debug, Clone)]
pub struct NodeCaps {
    pub driver: String,
    pub card: String,
    /// Capabilities of this node (`device_caps` when the driver reports it, else the device's).
    pub caps: u32,
}

fn c_string(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

pub fn query_caps(fd: c_int) -> io::Result<NodeCaps> {
    // SAFETY: v4l2_capability is plain old data (integers and byte arrays), so all-zero is a
    // valid value; VIDIOC_QUERYCAP writes exactly one v4l2_capability through the pointer,
    // which points to a live, writable, correctly sized local.
    let cap = unsafe {
        let mut cap: v4l2_capability = mem::zeroed();
        ioctl(fd, vidioc::VIDIOC_QUERYCAP, (&raw mut cap).cast::<c_void>())?;
        cap
    };
    let caps = if cap.capabilities & V4L2_CAP_DEVICE_CAPS != 0 {
        cap.device_caps
    } else {
        cap.capabilities
    };
    Ok(NodeCaps {
        driver: c_string(&cap.driver),
        card: c_string(&cap.card),
        caps,
    })
}

/// Range of one integer or menu control, in the driver's units.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControlRange {
    pub min: i64,
    pub max: i64,
    pub step: u64,
    pub default: i64,
}

impl ControlRange {
    /// The value the driver will store for `value`: clamped to the range and rounded to the
    /// nearest step from the minimum (V4L2 "Extended Controls": drivers adjust, not reject).
    pub fn adjust(&self, value: i64) -> i64 {
        let value = value.clamp(self.min, self.max);
        let step = i64::try_from(self.step.max(1)).unwrap_or(1);
        let steps = (value - self.min + step / 2) / step;
        (self.min + steps * step).min(self.max)
    }

    pub fn contains(&self, value: i64) -> bool {
        (self.min..=self.max).contains(&value)
    }
}

/// The range of control `id`, or `None` when the device has no such control (or it is disabled
/// or read-only, so it cannot be set).
pub fn query_control(fd: c_int, id: u32) -> io::Result<Option<ControlRange>> {
    // SAFETY: v4l2_query_ext_ctrl is plain old data, so all-zero is valid; the kernel reads `id`
    // and writes one v4l2_query_ext_ctrl through the pointer to this live local.
    let result = unsafe {
        let mut query: v4l2_query_ext_ctrl = mem::zeroed();
        query.id = id;
        ioctl(
            fd,
            vidioc::VIDIOC_QUERY_EXT_CTRL,
            (&raw mut query).cast::<c_void>(),
        )
        .map(|()| query)
    };
    match result {
        Ok(query) if query.flags & (V4L2_CTRL_FLAG_DISABLED | V4L2_CTRL_FLAG_READ_ONLY) != 0 => {
            Ok(None)
        }
        Ok(query) => Ok(Some(ControlRange {
            min: query.minimum,
            max: query.maximum,
            step: query.step,
            default: query.default_value,
        })),
        // EINVAL: no such control.
        Err(error) if error.kind() == io::ErrorKind::InvalidInput => Ok(None),
        Err(error) => Err(error),
    }
}
