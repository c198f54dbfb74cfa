//! Pose validation and the roll-pitch-yaw edge conversions.
//!
//! Inside the core every orientation is a unit quaternion and every composition is a rotation product.
//! Roll-pitch-yaw only exists at the edges (state and action vectors), so the conversions here are written
//! to round-trip to machine precision everywhere, including at ±90° pitch where the angles themselves are
//! not unique.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::f64::consts::{PI, TAU};

/// Largest accepted deviation of a wire quaternion's norm from 1; smaller deviations are renormalised.
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// Why a pose was refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum PoseError {
    #[error("position is not finite: {0:?}")]
    NonFinitePosition([f64; 3]),
    #[error("orientation is not finite: {0:?}")]
    NonFiniteOrientation([f64; 4]),
    #[error("quaternion norm {norm} differs from 1 by more than {QUATERNION_NORM_TOLERANCE}")]
    NonUnitQuaternion { norm: f64 },
}

/// Builds a pose from wire values (metres, quaternion x y z w), rejecting NaN, infinities and quaternions
/// whose norm is off by more than [`QUATERNION_NORM_TOLERANCE`]; smaller deviations are renormalised.
pub fn validate_pose(position_m: [f64; 3], quat_xyzw: [f64; 4]) -> Result<Isometry3<f64>, PoseError> {
    if position_m.iter().any(|v| !v.is_finite()) {
        return Err(PoseError::NonFinitePosition(position_m));
    }
    if quat_xyzw.iter().any(|v| !v.is_finite()) {
        return Err(PoseError::NonFiniteOrientation(quat_xyzw));
    }
    let [x, y, z, w] = quat_xyzw;
    let q = Quaternion::new(w, x, y, z);
    let norm = q.norm();
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(PoseError::NonUnitQuaternion { norm });
    }
    Ok(Isometry3::from_parts(
        Translation3::new(position_m[0], position_m[1], position_m[2]),
        UnitQuaternion::new_normalize(q),
    ))
}

/// Re-checks a pose that is already an `Isometry3`: values built with `new_unchecked` or by arithmetic on
/// bad input can still carry NaN or a drifted quaternion.
pub fn check_pose(pose: &Isometry3<f64>) -> Result<(), PoseError> {
    let p = pose.translation.vector;
    let q = pose.rotation.quaternion();
    let position_m = [p.x, p.y, p.z];
    let quat = [q.i, q.j, q.k, q.w];
    if position_m.iter().any(|v| !v.is_finite()) {
        return Err(PoseError::NonFinitePosition(position_m));
    }
    if quat.iter().any(|v| !v.is_finite()) {
        return Err(PoseError::NonFiniteOrientation(quat));
    }
    let norm = q.norm();
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(PoseError::NonUnitQuaternion { norm });
    }
    Ok(())
}

/// Wire form of a pose: position (m) and quaternion (x, y, z, w).
pub fn pose_to_wire(pose: &Isometry3<f64>) -> ([f64; 3], [f64; 4]) {
    let p = pose.translation.vector;
    let q = pose.rotation.quaternion();
    ([p.x, p.y, p.z], [q.i, q.j, q.k, q.w])
}

/// Wraps an angle to (−π, π] using `(θ + π) mod 2π − π`, folding the single point −π onto +π.
pub fn wrap_angle_rad(angle_rad: f64) -> f64 {
    let wrapped = (angle_rad + PI).rem_euclid(TAU) - PI;
    if wrapped <= -PI { wrapped + TAU } else { wrapped }
}

/// Angle of a rotation in [0, π]. Uses `atan2` rather than `acos(w)`, which loses half the digits near zero
/// and would make a 1e-9 round-trip check meaningless.
pub fn rotation_angle_rad(rotation: &UnitQuaternion<f64>) -> f64 {
    let q = rotation.quaternion();
    2.0 * q.imag().norm().atan2(q.w.abs())
}

/// Angle of the rotation taking `from` to `to`, in [0, π].
pub fn angle_between_rad(from: &UnitQuaternion<f64>, to: &UnitQuaternion<f64>) -> f64 {
    rotation_angle_rad(&(from.inverse() * to))
}

/// Rotation from extrinsic roll (about x), then pitch (about y), then yaw (about z):
/// `R = Rz(yaw)·Ry(pitch)·Rx(roll)`.
pub fn rotation_from_rpy(rpy_rad: [f64; 3]) -> UnitQuaternion<f64> {
    let [roll, pitch, yaw] = rpy_rad;
    let (sr, cr) = (0.5 * roll).sin_cos();
    let (sp, cp) = (0.5 * pitch).sin_cos();
    let (sy, cy) = (0.5 * yaw).sin_cos();
    UnitQuaternion::new_unchecked(Quaternion::new(
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ))
}

/// Roll, pitch, yaw (rad) with `R = Rz(yaw)·Ry(pitch)·Rx(roll)`, pitch in [−π/2, π/2].
///
/// Pitch and yaw come from the first column; roll is then fitted to the residual `Ry(p)ᵀ·Rz(y)ᵀ·R`. Near
/// ±90° pitch the yaw read from the first column is noise, but at that pose a yaw error is a roll error, so
/// fitting roll afterwards absorbs it and `rotation_from_rpy(rpy_from_rotation(q))` stays exact.
pub fn rpy_from_rotation(rotation: &UnitQuaternion<f64>) -> [f64; 3] {
    let m = rotation.to_rotation_matrix();
    let m = m.matrix();
    let pitch = (-m[(2, 0)]).atan2(m[(0, 0)].hypot(m[(1, 0)]));
    let yaw = m[(1, 0)].atan2(m[(0, 0)]);
    // Second column of Ry(−pitch)·Rz(−yaw)·R, written out: only its y and z entries are needed.
    let (sp, cp) = pitch.sin_cos();
    let (sy, cy) = yaw.sin_cos();
    let residual_11 = -sy * m[(0, 1)] + cy * m[(1, 1)];
    let residual_21 = sp * (cy * m[(0, 1)] + sy * m[(1, 1)]) + cp * m[(2, 1)];
    let roll = residual_21.atan2(residual_11);
    [roll, pitch, yaw]
}

/// Position of a pose as an array (m).
pub fn position_m(pose: &Isometry3<f64>) -> [f64; 3] {
    let p = pose.translation.vector;
    [p.x, p.y, p.z]
}

/// Distance between the positions of two poses (m) and the angle between their orientations (rad).
pub fn pose_distance(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    (
        (a.translation.vector - b.translation.vector).norm(),
        angle_between_rad(&a.rotation, &b.rotation),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use proptest::prelude::*;
    use std::f64::consts::FRAC_PI_2;

    #[test]
    fn validate_rejects_bad_input_and_renormalises_small_drift() {
        assert!(matches!(
            validate_pose([f64::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            Err(PoseError::NonFinitePosition(_))
        ));
        assert!(matches!(
            validate_pose([0.0; 3], [0.0, f64::INFINITY, 0.0, 1.0]),
            Err(PoseError::NonFiniteOrientation(_))
        ));
        assert!(matches!(
            validate_pose([0.0; 3], [0.0, 0.0, 0.0, 0.0]),
            Err(PoseError::NonUnitQuaternion { .. })
        ));
        assert!(matches!(
            validate_pose([0.0; 3], [0.0, 0.0, 0.0, 1.002]),
            Err(PoseError::NonUnitQuaternion { .. })
        ));
        let pose = validate_pose([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0005]).unwrap();
        assert!((pose.rotation.quaternion().norm() - 1.0).abs() < 1e-15);
        assert!((Vector3::from(position_m(&pose)) - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-15);
    }

    #[test]
    fn rpy_matches_the_extrinsic_xyz_convention() {
        let (roll, pitch, yaw) = (0.3, -0.7, 2.1);
        let expected = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw)
            * Rotation3::from_axis_angle(&Vector3::y_axis(), pitch)
            * Rotation3::from_axis_angle(&Vector3::x_axis(), roll);
        let q = rotation_from_rpy([roll, pitch, yaw]);
        assert!((q.to_rotation_matrix().matrix() - expected.matrix()).abs().max() < 1e-15);
        let rpy = rpy_from_rotation(&q);
        assert!(
            (rpy[0] - roll).abs() < 1e-12 && (rpy[1] - pitch).abs() < 1e-12 && (rpy[2] - yaw).abs() < 1e-12
        );
    }

    #[test]
    fn wrap_covers_the_half_open_interval() {
        assert!((wrap_angle_rad(PI) - PI).abs() < 1e-15);
        assert!((wrap_angle_rad(-PI) - PI).abs() < 1e-15);
        assert!((wrap_angle_rad(3.0 * PI / 2.0) + FRAC_PI_2).abs() < 1e-12);
        assert!((wrap_angle_rad(-7.0) - (-7.0 + TAU)).abs() < 1e-12);
        assert!(wrap_angle_rad(0.0).abs() < 1e-300);
    }

    fn any_rotation() -> impl Strategy<Value = UnitQuaternion<f64>> {
        (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)
            .prop_filter("non-zero", |(a, b, c, d)| a * a + b * b + c * c + d * d > 1e-3)
            .prop_map(|(w, x, y, z)| UnitQuaternion::new_normalize(Quaternion::new(w, x, y, z)))
    }

    fn near_gimbal_lock() -> impl Strategy<Value = UnitQuaternion<f64>> {
        (-PI..PI, prop::bool::ANY, -1e-6..1e-6f64, -PI..PI).prop_map(|(roll, up, dp, yaw)| {
            let pitch = if up { FRAC_PI_2 } else { -FRAC_PI_2 } + dp;
            rotation_from_rpy([roll, pitch, yaw])
        })
    }

    proptest! {
        #[test]
        fn rpy_round_trip_is_exact(q in any_rotation()) {
            let back = rotation_from_rpy(rpy_from_rotation(&q));
            prop_assert!(angle_between_rad(&q, &back) < 1e-12);
        }

        #[test]
        fn rpy_round_trip_is_exact_near_ninety_degrees_pitch(q in near_gimbal_lock()) {
            let rpy = rpy_from_rotation(&q);
            prop_assert!(rpy.iter().all(|a| a.is_finite()));
            let back = rotation_from_rpy(rpy);
            prop_assert!(angle_between_rad(&q, &back) < 1e-12);
        }

        #[test]
        fn wrap_lands_in_range_and_preserves_the_angle(a in -100.0..100.0f64) {
            let w = wrap_angle_rad(a);
            prop_assert!(w > -PI && w <= PI);
            let turns = (a - w) / TAU;
            prop_assert!((turns - turns.round()).abs() < 1e-9);
        }
    }
}
