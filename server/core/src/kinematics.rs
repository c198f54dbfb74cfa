//! Forward and inverse kinematics of the supported arms.
