"""A phone2act arm as a LeRobot `Robot` (type `phone2act`), discovered by lerobot's plugin mechanism."""

from lerobot_robot_phone2act.arm_watch import ABSOLUTE_EE_NAMES, ArmWatch, GateRefusal, rotation_6d
from lerobot_robot_phone2act.config_phone2act_robot import Phone2ActRobotConfig
from lerobot_robot_phone2act.phone2act_robot import Phone2ActRobot

__all__ = ["ABSOLUTE_EE_NAMES", "ArmWatch", "GateRefusal", "Phone2ActRobot", "Phone2ActRobotConfig", "rotation_6d"]
