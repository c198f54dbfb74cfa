"""A phone through phone2act as a LeRobot `Teleoperator` (type `phone2act`)."""

from lerobot_teleoperator_phone2act.config_phone2act_teleop import Phone2ActTeleopConfig
from lerobot_teleoperator_phone2act.phone2act_teleop import Phone2ActTeleop

__all__ = ["Phone2ActTeleop", "Phone2ActTeleopConfig"]
