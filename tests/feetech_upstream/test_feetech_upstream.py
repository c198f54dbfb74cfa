"""lerobot's own Feetech client (`FeetechMotorsBus` on feetech-servo-sdk, and `SO101Follower`) against phone2act's
Feetech bus emulator, and phone2act's SO-101 bridge against lerobot on the same bus and calibration file.

If lerobot can find, set up, calibrate, configure, read and drive the emulated servos, the emulator speaks what
the SDK expects (broadcast ping, id change, firmware and model registers, Phase, alarms); if phone2act's bridge
then reads the angles lerobot reads, the two agree on the calibration file and the wire.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from conftest import Emulator, so101_check
from lerobot.motors import Motor, MotorNormMode
from lerobot.motors.feetech import FeetechMotorsBus
from lerobot.robots.so_follower import SO101Follower, SO101FollowerConfig

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
# Shaft positions (raw counts) of a factory-fresh arm, away from 2047 so homing has something to do.
START = {1: 2100, 2: 1900, 3: 2200, 4: 2000, 5: 3000, 6: 2500}
OVERLOAD, VOLTAGE, OVERHEAT = 0x20, 0x01, 0x04
PHASE = "18 1"


def servo_args(*extra: str) -> list[str]:
    args = [a for id_, raw in START.items() for a in ("--servo", f"{id_}:{raw}")]
    return [*args, *extra]


def make_bus(port: str, motors: dict[str, int] | None = None) -> FeetechMotorsBus:
    motors = motors or {name: i + 1 for i, name in enumerate(JOINTS)}
    return FeetechMotorsBus(
        port=port,
        motors={
            name: Motor(id_, "sts3215", MotorNormMode.RANGE_0_100 if name == "gripper" else MotorNormMode.DEGREES)
            for name, id_ in motors.items()
        },
    )


def follower(port: str, calibration_dir: Path) -> SO101Follower:
    return SO101Follower(SO101FollowerConfig(port=port, id="emulated", calibration_dir=calibration_dir))


def calibrate_by_hand(emu: Emulator, monkeypatch: pytest.MonkeyPatch, sweep: int = 600) -> None:
    """Makes lerobot's interactive calibration run unattended: every prompt is answered with Enter, and each
    check for Enter during the range recording moves the arm as an operator's hand would (each joint but the
    wrist roll to +sweep, then -sweep around where it stood), then presses Enter."""
    import lerobot.motors.motors_bus as motors_bus

    monkeypatch.setattr("builtins.input", lambda *_args: "")
    calls = {"n": 0}

    def hand() -> bool:
        step = calls["n"]
        calls["n"] += 1
        if step < 2:
            for id_ in (1, 2, 3, 4, 6):
                emu.cmd(f"move {id_} {START[id_] + (sweep if step == 0 else -sweep)}")
            return False
        return True

    monkeypatch.setattr(motors_bus, "enter_pressed", hand)


def positions_line(result) -> dict[str, float]:
    for line in result.stdout.splitlines():
        if line.startswith("positions "):
            return json.loads(line.removeprefix("positions "))
    raise AssertionError(f"no positions in so101-check output:\n{result.stdout}\n{result.stderr}")


def test_broadcast_ping_finds_every_servo_with_its_model(start_emulator) -> None:
    emu = start_emulator(*servo_args())
    bus = make_bus(emu.port)
    bus.connect(handshake=False)
    try:
        assert bus.broadcast_ping() == {id_: 777 for id_ in START}
    finally:
        bus.disconnect(disable_torque=False)


def test_handshake_checks_models_and_one_firmware_version(start_emulator) -> None:
    emu = start_emulator(*servo_args())
    bus = make_bus(emu.port)
    bus.connect()
    try:
        assert bus._read_firmware_version(bus.ids) == {id_: "3.10" for id_ in START}
    finally:
        bus.disconnect(disable_torque=False)


def test_setup_motor_gives_a_factory_servo_its_id(start_emulator) -> None:
    # One servo on the bus, with the factory id 1, as `lerobot-setup-motors` asks for.
    emu = start_emulator("--servo", "1:2047")
    bus = make_bus(emu.port, {"gripper": 6})
    bus.setup_motor("gripper")
    try:
        assert emu.cmd("ids") == "6"
        assert bus.ping("gripper") == 777
    finally:
        bus.disconnect(disable_torque=False)


def test_so101_follower_calibrates_configures_observes_acts_and_phone2act_reads_the_same(
    start_emulator, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # The wrist roll arrives in multi-turn feedback mode, as some STS3215s do.
    emu = start_emulator(*servo_args("--multi-turn", "5"))
    # The hand holds the arm until the first action: enabling torque must not pull it toward a stale goal.
    for id_ in START:
        emu.cmd(f"speed {id_} 0")
    calibrate_by_hand(emu, monkeypatch)
    robot = follower(emu.port, tmp_path)
    robot.connect(calibrate=True)
    try:
        cal_file = tmp_path / "emulated.json"
        calibration = json.loads(cal_file.read_text())
        assert calibration["shoulder_pan"]["homing_offset"] == START[1] - 2047
        assert (calibration["shoulder_pan"]["range_min"], calibration["shoulder_pan"]["range_max"]) == (1447, 2647)
        assert (calibration["wrist_roll"]["range_min"], calibration["wrist_roll"]["range_max"]) == (0, 4095)
        # configure() cleared Phase bit 4.
        assert emu.cmd(f"get 5 {PHASE}") == "0"

        obs = robot.get_observation()
        # The hand left every swept joint 600 counts below the middle of its range.
        assert obs["shoulder_pan.pos"] == pytest.approx(-600 * 360 / 4095)
        action = {k: v for k, v in obs.items()}
        action["shoulder_pan.pos"] = 10.0
        action["gripper.pos"] = 80.0
        robot.send_action(action)
        for id_ in START:
            emu.cmd(f"speed {id_} 4000")
        # The emulated servo moves at 4000 counts/s; 5 s leaves room for a loaded machine.
        deadline = time.monotonic() + 5
        while abs(robot.get_observation()["shoulder_pan.pos"] - 10.0) > 0.1:
            assert time.monotonic() < deadline, "shoulder_pan never reached 10 degrees"
            time.sleep(0.02)
    finally:
        robot.disconnect()

    # A swapped wrist servo in multi-turn mode, turned past the seam while the arm is off.
    emu.cmd(f"set 5 {PHASE} 16")
    offset = calibration["wrist_roll"]["homing_offset"]
    emu.cmd(f"move 5 {offset + 4096 + 150}")
    assert int(emu.cmd("present 5")) == 4096 + 150

    # phone2act's bridge reads the bus first, without configuring it (the bit stays set) ...
    phone2act = positions_line(so101_check("--port", emu.port, "--calibration", cal_file, "--positions"))
    # ... then lerobot, which clears the bit when it connects: both see the same angles. Its connect turns the
    # torque on, and the servos would head for their last goals: the hand holds the arm still.
    for id_ in START:
        emu.cmd(f"speed {id_} 0")
    robot = follower(emu.port, tmp_path)
    robot.connect(calibrate=True)
    try:
        lerobot_obs = robot.get_observation()
    finally:
        robot.disconnect()
    assert set(phone2act) == {f"{j}.pos" for j in JOINTS}
    for key, value in lerobot_obs.items():
        assert phone2act[key] == pytest.approx(value, abs=1e-9), key
    assert lerobot_obs["wrist_roll.pos"] == pytest.approx((150 - 2047.5) * 360 / 4095)


def test_alarms_lerobot_keeps_reading_and_phone2act_warns_or_stops(
    start_emulator, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    emu = start_emulator(*servo_args())
    # The arm stays where the hand left it, so lerobot and phone2act read it at one pose.
    for id_ in START:
        emu.cmd(f"speed {id_} 0")
    calibrate_by_hand(emu, monkeypatch)
    robot = follower(emu.port, tmp_path)
    robot.connect(calibrate=True)
    cal_file = tmp_path / "emulated.json"
    try:
        # The gripper squeezes an object; a 7.4 V shoulder servo sits on a 12 V supply.
        emu.cmd(f"alarm 6 {OVERLOAD}")
        emu.cmd(f"alarm 1 {VOLTAGE}")
        obs = robot.get_observation()
        robot.send_action(obs)
        assert set(robot.get_observation()) == {f"{j}.pos" for j in JOINTS}
        # Its single-servo writes, though, take any alarm for a failure: disconnecting (torque off) raises.
        with pytest.raises(RuntimeError, match="Input voltage error"):
            robot.disconnect()
    finally:
        robot.bus.port_handler.closePort()

    check = so101_check("--port", emu.port, "--calibration", cal_file, "--positions")
    assert check.returncode == 0, check.stdout + check.stderr
    warning = "bridge warning: servo 1 (shoulder_pan): input voltage (0x01); servo 6 (gripper): overload (0x20)"
    assert warning in check.stdout
    assert positions_line(check)["shoulder_pan.pos"] == pytest.approx(obs["shoulder_pan.pos"], abs=1e-9)

    # lerobot's handshake takes a servo reporting an alarm for a missing one: it will not connect.
    robot = follower(emu.port, tmp_path)
    with pytest.raises(RuntimeError, match="Missing motor IDs"):
        robot.connect(calibrate=False)
    robot.bus.port_handler.closePort()

    # An alarm that stops the arm: the check fails and names the servo.
    emu.cmd(f"alarm 3 {OVERHEAT}")
    check = so101_check("--port", emu.port, "--calibration", cal_file)
    assert check.returncode == 1
    assert "servo 3 (elbow_flex)" in check.stdout and "FAIL alarm overheat (0x04): stops the arm" in check.stdout
