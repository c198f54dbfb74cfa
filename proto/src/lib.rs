//! The phone2act.v1 gRPC API: message types and service stubs generated from `proto/phone2act/v1/*.proto`,
//! the encoded file descriptor set (for gRPC server reflection), and the one wire boundary: conversions between
//! wire messages and core types (`convert_*`), the latest-wins sample fold ([`sample`]) and the button
//! builders ([`buttons`]) that the server, the SDK and the gateway all use.

pub mod buttons;
pub mod convert_arm;
pub mod convert_camera;
pub mod convert_episode;
pub mod convert_policy;
pub mod sample;

pub use convert_episode::MAX_TASK_BYTES;
pub use sample::PendingSample;

/// Generated code for package `phone2act.v1`.
#[allow(clippy::pedantic, clippy::all, missing_docs)]
pub mod v1 {
    tonic::include_proto!("phone2act.v1");
}

/// Encoded `FileDescriptorSet` of every phone2act.v1 file, for gRPC reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("phone2act_v1_descriptor");

/// A wire value that has no meaning here.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConvertError {
    /// An enum field holds a value this version does not know (or the unset value where one is required).
    #[error("unknown {what} {value}")]
    UnknownEnum { what: &'static str, value: i32 },
}

/// Fully qualified gRPC service names, as health checks and reflection report them.
pub const SERVICE_NAMES: [&str; 7] = [
    "phone2act.v1.Teleop",
    "phone2act.v1.Policy",
    "phone2act.v1.Episodes",
    "phone2act.v1.System",
    "phone2act.v1.Bridge",
    "phone2act.v1.Cameras",
    "phone2act.v1.Scene",
];

impl v1::Vec3 {
    /// A vector from its three components.
    pub fn new(x: f64, y: f64, z: f64) -> Self {
        Self { x, y, z }
    }
}

impl v1::Quaternion {
    /// The identity rotation.
    pub fn identity() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

impl v1::Pose {
    /// A pose from a position in metres and a quaternion (x, y, z, w).
    pub fn from_parts(position_m: [f64; 3], quat_xyzw: [f64; 4]) -> Self {
        Self {
            position_m: Some(v1::Vec3::new(position_m[0], position_m[1], position_m[2])),
            orientation: Some(v1::Quaternion {
                x: quat_xyzw[0],
                y: quat_xyzw[1],
                z: quat_xyzw[2],
                w: quat_xyzw[3],
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;

    #[test]
    fn descriptor_set_names_every_service() {
        let text = String::from_utf8_lossy(FILE_DESCRIPTOR_SET);
        for name in SERVICE_NAMES {
            let short = name.rsplit('.').next().unwrap();
            assert!(text.contains(short), "descriptor set lacks service {name}");
        }
    }

    #[test]
    fn pose_round_trips_through_the_wire() {
        let pose = v1::Pose::from_parts([0.1, -0.2, 0.3], [0.0, 0.0, 0.0, 1.0]);
        let bytes = pose.encode_to_vec();
        let back = v1::Pose::decode(bytes.as_slice()).unwrap();
        assert_eq!(back, pose);
    }
}
