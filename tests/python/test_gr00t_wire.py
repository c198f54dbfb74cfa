"""The GR00T wire codec, dialect detection and embodiment mapping (no phone2act server needed).

N1.5 against the golden bytes GR00T N1.5 wrote, N1.7 against those its tag and its main branch wrote (both codecs);
N1.5, N1.6 and N1.7 against the stand-in servers; the pickle-era server's bytes refused with a message naming it.
"""

from __future__ import annotations

import io
import types

import msgpack
import numpy as np
import pytest
from conftest import golden
from gr00t_standin import PolicyStandIn, ReplayStandIn, StandIn, torch_save_like
from phone2act import ABSOLUTE_EE, DELTA_EE, ArmLayout
from phone2act.v1 import common_pb2, policy_pb2
from phone2act_gr00t import (
    MSGPACK_NUMPY,
    N15,
    N16,
    N16_SIM,
    N17,
    NPY,
    ActionModeError,
    ChunkShapeError,
    Embodiment,
    EmbodimentMismatch,
    Gr00tClient,
    Gr00tError,
    Gr00tProtocolError,
    Gr00tTimeout,
    ObservationError,
    action_mode_of,
    check_forced_wire,
)
from phone2act_gr00t.wire import decode_reply, packb, request, unpackb

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
STATE = JOINTS + ("ee_x", "ee_y", "ee_z", "ee_roll", "ee_pitch", "ee_yaw", "gripper")
DELTA_NAMES = ("delta_x", "delta_y", "delta_z", "delta_roll", "delta_pitch", "delta_yaw", "gripper")
ABS_NAMES = ("x", "y", "z", "roll", "pitch", "yaw", "gripper")
LAYOUT = ArmLayout("main", STATE, DELTA_NAMES)
NAMES = ["request_ping", "response_ping", "request_get_action", "response_get_action", "response_error"]


@pytest.mark.parametrize("name", NAMES)
def test_golden_messages_round_trip_byte_exact(name: str) -> None:
    raw = golden(f"{name}.msgpack")
    hexed = golden(f"{name}.hex").decode().split()
    assert bytes.fromhex("".join(hexed)) == raw, "the .hex and .msgpack goldens disagree"
    assert packb(unpackb(raw)) == raw


def test_ping_request_is_golden() -> None:
    assert request("ping") == golden("request_ping.msgpack")


def arm_obs(arm: str = "main", state: list[float] | None = None, actions: tuple[str, ...] = DELTA_NAMES,
            ) -> policy_pb2.ArmObservation:
    state = state or [0.1, 0.2, 0.3, 0.4, 0.5, 0.2, 0.0, 0.15, 3.1, 0.2, 0.0, 0.9]
    return policy_pb2.ArmObservation(arm=arm, state=state, state_names=STATE, action_names=actions)


def observation_like_golden() -> policy_pb2.Observation:
    """The phone2act observation that, mapped with GR00T's so100 keys, is the golden get_action request."""
    frame = common_pb2.CameraFrame(camera="webcam", width=2, height=2,
                                   encoding=common_pb2.IMAGE_ENCODING_RGB8, data=bytes(12))
    return policy_pb2.Observation(observation_id=7, arms=[arm_obs()], frames=[frame], task="pick the red cube")


def test_request_built_from_an_observation_is_the_golden_request() -> None:
    emb = Embodiment.so100(LAYOUT, camera="webcam")
    obs = observation_like_golden()
    data = emb.request_data(obs, obs.task, N15)
    assert request("get_action", data) == golden("request_get_action.msgpack")


def test_n16_request_is_nested_batched_and_float32() -> None:
    emb = Embodiment.so100(LAYOUT, camera="webcam")
    data = emb.request_data(observation_like_golden(), "pick the red cube", N16)
    assert set(data) == {"observation", "options"}
    o = data["observation"]
    assert set(o) == {"video", "state", "language"}
    assert o["video"]["webcam"].shape == (1, 1, 2, 2, 3) and o["video"]["webcam"].dtype == np.uint8
    assert o["state"]["single_arm"].shape == (1, 1, 5) and o["state"]["single_arm"].dtype == np.float32
    np.testing.assert_allclose(o["state"]["single_arm"][0, 0], [0.1, 0.2, 0.3, 0.4, 0.5], rtol=1e-6)
    assert o["language"] == {"annotation.human.task_description": [["pick the red cube"]]}
    # It survives the wire unchanged.
    back = unpackb(request("get_action", data))["data"]["observation"]
    np.testing.assert_array_equal(back["state"]["gripper"], o["state"]["gripper"])


def test_request_needs_rgb8_frames_and_known_state() -> None:
    obs = observation_like_golden()
    obs.frames[0].encoding = common_pb2.IMAGE_ENCODING_JPEG
    with pytest.raises(ObservationError, match="IMAGE_ENCODING_JPEG"):
        Embodiment.so100(LAYOUT, camera="webcam").request_data(obs, "t")
    with pytest.raises(ObservationError, match="camera 'front'"):
        Embodiment.so100(LAYOUT, camera="front").request_data(observation_like_golden(), "t")


def test_golden_answer_becomes_a_full_chunk() -> None:
    answer = unpackb(golden("response_get_action.msgpack"))
    steps = Embodiment.so100(LAYOUT, camera="webcam", action_scale=0.001).chunk_steps(answer, LAYOUT)
    assert steps.shape == (16, 7)
    expected = np.arange(80, dtype=np.float64).reshape(16, 5) * 0.001
    np.testing.assert_allclose(steps[:, :5], expected, atol=1e-9)
    assert np.all(steps[:, 5] == 0) and np.all(steps[:, 6] == 0)
    assert Embodiment.so100(LAYOUT, "webcam").chunk_steps(answer, LAYOUT, max_steps=8).shape == (8, 7)


def test_n16_answer_is_action_info_pair_with_bare_batched_keys() -> None:
    emb = Embodiment.phone2act(LAYOUT)
    arm = np.arange(96, dtype=np.float32).reshape(1, 16, 6)
    answer = [{"arm": arm, "gripper": np.ones((1, 16, 1), np.float32)}, {}]
    steps = emb.chunk_steps(answer, LAYOUT, wire=N16)
    np.testing.assert_array_equal(steps[:, :6], arm[0])
    assert np.all(steps[:, 6] == 1)
    with pytest.raises(ChunkShapeError, match=r"N1.6 answer is \[action, info\]"):
        emb.chunk_steps({"action.arm": arm}, LAYOUT, wire=N16)


def _answer_with(**arrays: np.ndarray) -> dict:
    return {f"action.{k}": v for k, v in arrays.items()}


def test_wrong_shapes_are_refused_with_the_shapes_named() -> None:
    emb = Embodiment.phone2act(LAYOUT)
    ok = _answer_with(arm=np.zeros((16, 6), np.float32), gripper=np.zeros((16, 1), np.float32))
    assert emb.chunk_steps(ok, LAYOUT).shape == (16, 7)
    squeezed = _answer_with(arm=np.zeros((16, 6), np.float32), gripper=np.zeros(16, np.float32))
    assert emb.chunk_steps(squeezed, LAYOUT).shape == (16, 7)
    cases = {
        "action arm has shape (16, 5); expected (horizon, 6)":
            _answer_with(arm=np.zeros((16, 5)), gripper=np.zeros((16, 1))),
        "has horizon 8, other groups 16": _answer_with(arm=np.zeros((16, 6)), gripper=np.zeros((8, 1))),
        "has no 'gripper' action": _answer_with(arm=np.zeros((16, 6))),
        "non-finite": _answer_with(arm=np.full((16, 6), np.nan), gripper=np.zeros((16, 1))),
    }
    for message, answer in cases.items():
        with pytest.raises(ChunkShapeError, match=message.replace("(", r"\(").replace(")", r"\)")):
            emb.chunk_steps(answer, LAYOUT)


def test_bimanual_groups_are_named_per_arm_and_split_back_per_arm() -> None:
    left, right = ArmLayout("left", STATE, DELTA_NAMES), ArmLayout("right", STATE, ABS_NAMES)
    emb = Embodiment.phone2act([left, right], ["front"])
    assert [g.key for g in emb.state] == ["left_arm", "left_gripper", "right_arm", "right_gripper"]
    assert [g.key for g in emb.actions] == ["left_arm", "left_gripper", "right_arm", "right_gripper"]
    assert emb.arms == ("left", "right")
    frame = common_pb2.CameraFrame(camera="front", width=1, height=1, encoding=common_pb2.IMAGE_ENCODING_RGB8,
                                   data=bytes(3))
    obs = policy_pb2.Observation(
        observation_id=3, frames=[frame],
        arms=[arm_obs("left", [float(i) for i in range(12)]),
              arm_obs("right", [float(10 + i) for i in range(12)], ABS_NAMES)])
    data = emb.request_data(obs, "hand over", N15)
    assert list(data) == ["video.front", "state.left_arm", "state.left_gripper", "state.right_arm",
                          "state.right_gripper", "annotation.human.task_description"]
    np.testing.assert_array_equal(data["state.right_arm"][0], np.arange(10, 21))
    np.testing.assert_array_equal(data["state.left_gripper"][0], [11])
    answer = _answer_with(left_arm=np.full((16, 6), 1.0), left_gripper=np.full((16, 1), 2.0),
                          right_arm=np.full((16, 6), 3.0), right_gripper=np.full((16, 1), 4.0))
    steps = emb.chunk_steps(answer, {"left": left, "right": right})
    assert set(steps) == {"left", "right"}
    assert np.all(steps["left"][:, :6] == 1) and np.all(steps["left"][:, 6] == 2)
    assert np.all(steps["right"][:, :6] == 3) and np.all(steps["right"][:, 6] == 4)


def test_action_mode_follows_what_the_server_reports() -> None:
    assert action_mode_of(arm_obs(actions=DELTA_NAMES)) == DELTA_EE
    assert action_mode_of(arm_obs(actions=ABS_NAMES)) == ABSOLUTE_EE
    # An explicit mode (when the server sends one) wins over the names.
    explicit = types.SimpleNamespace(arm="main", action_mode=ABSOLUTE_EE, action_names=DELTA_NAMES,
                                     state_names=STATE)
    assert action_mode_of(explicit) == ABSOLUTE_EE
    listed = types.SimpleNamespace(arm="main", action_mode=ABSOLUTE_EE)  # or on the arm's System.ListArms entry
    assert action_mode_of(arm_obs(actions=DELTA_NAMES), listed) == ABSOLUTE_EE
    assert action_mode_of(arm_obs(actions=DELTA_NAMES), types.SimpleNamespace(arm="main")) == DELTA_EE
    # Joint targets: the arm's joint names. Pushed as the SDK's joint mode, or refused if it has none.
    joints = arm_obs(actions=JOINTS + ("gripper",))
    joint_modes = [v for n, v in policy_pb2.ActionMode.items() if "JOINT" in n]
    if joint_modes:
        assert action_mode_of(joints) == joint_modes[0]
    else:
        with pytest.raises(ActionModeError, match="joint actions, but this phone2act SDK has no such ActionMode"):
            action_mode_of(joints)
    with pytest.raises(ActionModeError, match=r"cannot tell the action representation of arm 'main'"):
        action_mode_of(arm_obs(actions=("a", "b", "gripper")))


def test_absolute_arm_refuses_an_answer_that_leaves_axes_unset() -> None:
    layout = ArmLayout("main", STATE, ABS_NAMES)
    answer = unpackb(golden("response_get_action.msgpack"))
    emb = Embodiment.so100(layout, "webcam")
    with pytest.raises(ChunkShapeError, match=r"takes absolute actions and the model gives no \['yaw'\]"):
        emb.chunk_steps(answer, layout, modes={"main": ABSOLUTE_EE})
    # The same answer on a delta arm leaves yaw at 0, which means "no rotation".
    delta = Embodiment.so100(LAYOUT, "webcam")
    assert delta.chunk_steps(answer, LAYOUT, modes={"main": DELTA_EE}).shape == (16, 7)


def test_client_against_the_golden_stand_in() -> None:
    with StandIn() as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        assert c.ping()
        answer = c.get_action(unpackb(golden("request_get_action.msgpack"))["data"])
        assert set(answer) == {"action.single_arm", "action.gripper"}
        assert answer["action.single_arm"].dtype == np.float32 and answer["action.single_arm"].shape == (16, 5)
        with pytest.raises(Gr00tError, match="Unknown endpoint: foo"):
            c.call("foo")
        # The stand-in received exactly what the upstream client would have sent.
        assert standin.requests[0] == golden("request_ping.msgpack")
        assert standin.requests[1] == golden("request_get_action.msgpack")
        c.close()


@pytest.mark.parametrize("wire", [N15, N16])
def test_dialect_is_detected_from_the_modality_config(wire: str) -> None:
    with PolicyStandIn(wire, video=("webcam",), state=("single_arm", "gripper"),
                       action=("single_arm", "gripper")) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        found, config = c.detect_wire()
        assert found == wire
        assert config is not None and set(config) == {"video", "state", "action", "language"}
        assert len(config["action"].delta_indices) == 16
        emb = Embodiment.so100(LAYOUT, "webcam").check_against(config, wire)
        assert emb.language_key == "annotation.human.task_description"
        # The mapped request is what that server accepts, and its answer maps back to a chunk.
        answer = c.get_action(emb.request_data(observation_like_golden(), "pick", wire))
        assert emb.chunk_steps(answer, LAYOUT, wire=wire).shape == (16, 7)
        assert standin.observations[-1][1] == "pick"
        np.testing.assert_allclose(standin.observations[-1][0]["single_arm"], [0.1, 0.2, 0.3, 0.4, 0.5], rtol=1e-6)
        c.close()


def test_n16_sim_wrapper_server_wants_flat_keys() -> None:
    """N1.6 behind `--use-sim-policy-wrapper`: same envelope and config, flat keys inside `observation`."""
    with PolicyStandIn(N16_SIM, video=("webcam",), state=("single_arm", "gripper"),
                       action=("single_arm", "gripper")) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        wire, config = c.detect_wire()
        assert wire == N16  # indistinguishable from its config; the nested request says so
        emb = Embodiment.so100(LAYOUT, "webcam").check_against(config, wire)
        with pytest.raises(Gr00tError, match="Video key 'video.webcam' must be in observation"):
            c.get_action(emb.request_data(observation_like_golden(), "t", N16))
        data = emb.request_data(observation_like_golden(), "t", N16_SIM)
        assert set(data["observation"]) == {"video.webcam", "state.single_arm", "state.gripper",
                                            "annotation.human.task_description"}
        answer = c.get_action(data)
        assert set(answer[0]) == {"action.single_arm", "action.gripper"}
        assert emb.chunk_steps(answer, LAYOUT, wire=N16_SIM).shape == (16, 7)
        c.close()


def test_server_without_modality_config_is_taken_for_n15() -> None:
    with PolicyStandIn(N15, modality_endpoint=False) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        assert c.detect_wire() == (N15, None)
        c.close()


def test_wrong_dialect_is_named_by_the_server() -> None:
    """What each server says to the other dialect's request (the adapter turns these into advice)."""
    with PolicyStandIn(N16, video=("webcam",), state=("single_arm", "gripper")) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        flat = Embodiment.so100(LAYOUT, "webcam").request_data(observation_like_golden(), "t", N15)
        with pytest.raises(Gr00tError, match="unexpected keyword argument 'video.webcam'"):
            c.get_action(flat)
        c.close()


def test_mismatched_keys_are_named() -> None:
    with PolicyStandIn(N16, video=("ego_view",), state=("left_arm", "right_arm"),
                       action=("left_arm", "right_arm")) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        wire, config = c.detect_wire()
        with pytest.raises(EmbodimentMismatch, match=r"state keys \['left_arm', 'right_arm'\] \(the adapter sends "
                                                     r"\['arm', 'gripper'\]\)"):
            Embodiment.phone2act(LAYOUT, ["front"]).check_against(config, wire)
        c.close()


@pytest.mark.parametrize("stream", [False, True])
def test_pickle_era_server_is_named_not_a_msgpack_traceback(stream: bool) -> None:
    with PolicyStandIn("pickle", stream=stream) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        with pytest.raises(Gr00tProtocolError) as err:
            c.detect_wire()
        msg = str(err.value)
        assert "pre-2025-09-10 pickle wire format" in msg
        assert ("Upgrade it to GR00T N1.5 (tag n1.5-release, 4af2b62), N1.6 (release commit 4e62473) or N1.7 (tag "
            "n1.7-release 23ace64, and main 626af89 (msgpack-numpy))") in msg
        assert "ExtraData" not in msg
        c.close()
    # What msgpack alone makes of these bytes: the bare traceback this replaces.
    with pytest.raises((msgpack.ExtraData, ValueError)):
        msgpack.unpackb(torch_save_like({"error": "x"}, stream))


def test_june_2025_server_answering_bare_error_is_named() -> None:
    """The June-2025 (pickle-era) server answers `b"ERROR"` to a request it cannot unpickle: named as that server."""
    with PolicyStandIn("pickle-june") as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        with pytest.raises(Gr00tProtocolError) as err:
            c.detect_wire()
        msg = str(err.value)
        assert 'bare b"ERROR"' in msg and "pre-2025-09-10 pickle wire format" in msg, msg
        assert ("Upgrade it to GR00T N1.5 (tag n1.5-release, 4af2b62), N1.6 (release commit 4e62473) or N1.7 (tag "
            "n1.7-release 23ace64, and main 626af89 (msgpack-numpy))") in msg
        assert "not a GR00T msgpack message" not in msg
        c.close()


@pytest.mark.parametrize(("forced", "server", "advice"), [
    (N16, N15, "run with --gr00t-version n1.5"),
    (N16_SIM, N15, "run with --gr00t-version n1.5"),
    (N15, N16, "run with --gr00t-version n1.6 (or n1.6-sim"),
])
def test_a_forced_version_the_server_contradicts_is_named_as_the_mistake(forced: str, server: str,
                                                                         advice: str) -> None:
    with PolicyStandIn(server, video=("front",)) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=2.0)
        config = c.modality_config()
        with pytest.raises(Gr00tProtocolError) as err:
            check_forced_wire(forced, config, standin.endpoint)
        msg = str(err.value)
        assert f"--gr00t-version {forced} does not match" in msg and "The version is the mistake" in msg, msg
        assert advice in msg, msg
        # The matching version, and a server that tells nothing, pass.
        check_forced_wire(server, config, standin.endpoint)
        check_forced_wire(forced, None, standin.endpoint)
        c.close()


def test_an_absolute_model_on_a_relative_arm_is_told_to_set_absolute() -> None:
    """A model fine-tuned on a phone2act dataset answers the recorded absolute targets (9 arm columns)."""
    layout = ArmLayout("main", STATE, ("delta_x", "delta_y", "delta_z", "delta_rx", "delta_ry", "delta_rz", "gripper"))
    answer = {"action.arm": np.zeros((16, 9), np.float32), "action.gripper": np.zeros((16, 1), np.float32)}
    with pytest.raises(ChunkShapeError) as err:
        Embodiment.phone2act(layout).chunk_steps(answer, layout, modes={"main": DELTA_EE})
    msg = str(err.value)
    assert "expected (horizon, 6)" in msg and "trained on absolute targets" in msg, msg
    assert "Set action_mode = \"absolute\" on arm 'main'" in msg, msg
    # Another width is only a shape error: nothing suggests a mode.
    answer["action.arm"] = np.zeros((16, 4), np.float32)
    with pytest.raises(ChunkShapeError) as err:
        Embodiment.phone2act(layout).chunk_steps(answer, layout, modes={"main": DELTA_EE})
    assert "action_mode" not in str(err.value)


def test_bytes_of_no_known_format_are_refused_readably() -> None:
    with pytest.raises(Gr00tProtocolError, match=r"not a GR00T msgpack message .*first bytes 93 4e 55 4d"):
        decode_reply(b"\x93NUMPY-not-a-reply", "ping", "tcp://x:1")
    assert decode_reply(packb({}), "reset", "tcp://x:1") == {}  # an empty map (0x80) is msgpack, not pickle


def test_late_answer_times_out_and_the_next_call_works() -> None:
    with StandIn(delay_s=0.6) as standin:
        c = Gr00tClient(standin.endpoint, timeout_s=0.2)
        with pytest.raises(Gr00tTimeout, match=r"did not answer 'get_action' within 200 ms"):
            c.get_action({"state.x": np.zeros((1, 1))})
        # A REQ socket that missed its reply is replaced, so the client is usable again.
        assert c.ping(timeout_s=2.0)
        c.close()


def test_npy_payload_is_a_plain_npy_file() -> None:
    raw = msgpack.unpackb(golden("response_get_action.msgpack"))
    npy = raw["action.single_arm"]["as_npy"]
    assert npy[:6] == b"\x93NUMPY" and (len(npy) - 80 * 4) % 64 == 0
    assert np.load(io.BytesIO(npy)).shape == (16, 5)


# --- N1.7: the n1.7-release tag (N1.6's wire) and GR00T main (msgpack-numpy), golden bytes from both -------------

N17_NAMES = ["request_ping", "response_ping", "request_get_modality_config", "response_get_modality_config",
             "request_get_action", "response_get_action", "request_reset", "response_reset", "response_error"]
N17_BUILDS = {"tag": NPY, "main": MSGPACK_NUMPY}


def golden_n17(build: str, name: str) -> bytes:
    return golden(f"../gr00t_wire_n17/{build}/{name}.msgpack")


@pytest.mark.parametrize("build", sorted(N17_BUILDS))
@pytest.mark.parametrize("name", N17_NAMES)
def test_n17_golden_messages_round_trip_byte_exact(build: str, name: str) -> None:
    raw = golden_n17(build, name)
    hexed = golden(f"../gr00t_wire_n17/{build}/{name}.hex").decode().split()
    assert bytes.fromhex("".join(hexed)) == raw, "the .hex and .msgpack goldens disagree"
    assert packb(unpackb(raw), N17_BUILDS[build]) == raw


def test_the_n17_tag_speaks_n16s_wire_and_main_does_not() -> None:
    # The tag's request is what N1.6's codec writes; main's arrays are msgpack-numpy maps with bin keys.
    tag, main = golden_n17("tag", "request_get_action"), golden_n17("main", "request_get_action")
    assert b"__ndarray_class__" in tag and b"__ndarray_class__" not in main
    plain = msgpack.unpackb(main)
    arr = plain["data"]["observation"]["state"]["single_arm"]
    assert arr[b"nd"] is True and arr[b"type"] == "<f4" and arr[b"kind"] == b"" and arr[b"shape"] == [1, 1, 5]
    # Each build's arrays reach the other as plain maps, never as arrays: the codec must match the server.
    assert isinstance(unpackb(main, accept=(NPY,))["data"]["observation"]["state"]["single_arm"], dict)
    assert isinstance(unpackb(tag, accept=(MSGPACK_NUMPY,))["data"]["observation"]["state"]["single_arm"], dict)


@pytest.mark.parametrize("build", sorted(N17_BUILDS))
def test_n17_request_built_from_an_observation_is_the_golden_request(build: str) -> None:
    emb = Embodiment.so100(LAYOUT, camera="webcam")
    obs = observation_like_golden()
    codec = N17_BUILDS[build]
    assert request("get_action", emb.request_data(obs, obs.task, N17), codec=codec) == golden_n17(
        build, "request_get_action")
    assert request("ping", codec=codec) == golden_n17(build, "request_ping")
    assert request("get_modality_config", codec=codec) == golden_n17(build, "request_get_modality_config")


@pytest.mark.parametrize("build", sorted(N17_BUILDS))
def test_n17_golden_answer_becomes_a_full_chunk_and_its_config_names_the_codec(build: str) -> None:
    answer = unpackb(golden_n17(build, "response_get_action"))
    assert answer[1] == {"current_step": 0, "episode_length": 40, "episode_index": 0}
    steps = Embodiment.so100(LAYOUT, camera="webcam", action_scale=0.001).chunk_steps(answer, LAYOUT, wire=N17)
    np.testing.assert_allclose(steps[:, :5], np.arange(80, dtype=np.float64).reshape(16, 5) * 0.001, atol=1e-9)
    config = unpackb(golden_n17(build, "response_get_modality_config"))
    assert {c.codec for c in config.values()} == {N17_BUILDS[build]}
    assert config["action"].modality_keys == ("single_arm", "gripper")
    assert config["action"].extra["action_configs"][0]["rep"] == "ABSOLUTE"


def test_msgpack_numpy_object_arrays_are_refused_both_ways() -> None:
    with pytest.raises(TypeError, match="refusing"):
        packb({"a": np.array([{"x": 1}], dtype=object)}, MSGPACK_NUMPY)
    forged = msgpack.packb({b"nd": True, b"type": "|O", b"kind": b"O", b"shape": [1], b"data": b"\x80\x04N."})
    with pytest.raises(Gr00tProtocolError):
        decode_reply(forged, "get_action", "tcp://test")


@pytest.mark.parametrize("codec", [NPY, MSGPACK_NUMPY])
def test_detection_follows_the_config_marker_and_the_replay_stand_in_replays(codec: str) -> None:
    actions = {"single_arm": np.arange(200, dtype=np.float32).reshape(40, 5), "gripper": np.zeros((40, 1))}
    with ReplayStandIn([actions], codec=codec) as standin:
        client = Gr00tClient(standin.endpoint, timeout_s=2.0)
        wire, config = client.detect_wire()
        assert (wire, client.codec) == ((N16, NPY) if codec == NPY else (N17, MSGPACK_NUMPY))
        emb = Embodiment.so100(LAYOUT, camera="webcam").check_against(config, wire)
        data = emb.request_data(observation_like_golden(), "pick the red cube", wire)
        first, second = client.get_action(data), client.get_action(data)
        np.testing.assert_array_equal(first[0]["single_arm"][0], actions["single_arm"][:16])
        np.testing.assert_array_equal(second[0]["single_arm"][0], actions["single_arm"][16:32])
        assert second[1]["current_step"] == 16
        # Past the episode's end the last action repeats; reset goes back to step 0.
        third = client.get_action(data)
        np.testing.assert_array_equal(third[0]["single_arm"][0, 8:], np.repeat(actions["single_arm"][-1:], 8, 0))
        assert client.call("reset", {"options": None}) == {"episode_index": 0, "episode_length": 40,
                                                           "current_step": 0}
        client.close()


def test_a_forced_codec_the_server_does_not_read_is_named() -> None:
    actions = {"single_arm": np.zeros((20, 5), np.float32), "gripper": np.zeros((20, 1), np.float32)}
    with ReplayStandIn([actions], codec=MSGPACK_NUMPY) as standin:
        client = Gr00tClient(standin.endpoint, timeout_s=2.0, codec=NPY)
        wire, config = client.detect_wire()
        assert client.codec == NPY, "a forced codec stays"
        data = Embodiment.so100(LAYOUT, camera="webcam").request_data(observation_like_golden(), "t", wire)
        with pytest.raises(Gr00tError, match="must be a numpy array. Got <class 'dict'>"):
            client.get_action(data)
        client.close()
