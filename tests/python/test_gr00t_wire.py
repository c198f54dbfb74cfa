"""The GR00T wire codec and embodiment mapping against the golden messages (no phone2act server needed)."""

from __future__ import annotations

import io

import msgpack
import numpy as np
import pytest
from conftest import golden
from gr00t_standin import StandIn
from phone2act import ArmLayout
from phone2act.v1 import common_pb2, policy_pb2
from phone2act_gr00t import ChunkShapeError, Embodiment, Gr00tClient, Gr00tError, Gr00tTimeout, ObservationError
from phone2act_gr00t.wire import packb, request, unpackb

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
LAYOUT = ArmLayout(
    "main",
    JOINTS + ("ee_x", "ee_y", "ee_z", "ee_roll", "ee_pitch", "ee_yaw", "gripper"),
    ("delta_x", "delta_y", "delta_z", "delta_roll", "delta_pitch", "delta_yaw", "gripper"),
)
NAMES = ["request_ping", "response_ping", "request_get_action", "response_get_action", "response_error"]


@pytest.mark.parametrize("name", NAMES)
def test_golden_messages_round_trip_byte_exact(name: str) -> None:
    raw = golden(f"{name}.msgpack")
    hexed = golden(f"{name}.hex").decode().split()
    assert bytes.fromhex("".join(hexed)) == raw, "the .hex and .msgpack goldens disagree"
    assert packb(unpackb(raw)) == raw


def test_ping_request_is_golden() -> None:
    assert request("ping") == golden("request_ping.msgpack")


def observation_like_golden() -> policy_pb2.Observation:
    """The phone2act observation that, mapped with GR00T's so100 keys, is the golden get_action request."""
    state = [0.1, 0.2, 0.3, 0.4, 0.5, 0.2, 0.0, 0.15, 3.1, 0.2, 0.0, 0.9]
    arm = policy_pb2.ArmObservation(arm="main", state=state, state_names=LAYOUT.state_names,
                                    action_names=LAYOUT.action_names)
    frame = common_pb2.CameraFrame(camera="webcam", width=2, height=2,
                                   encoding=common_pb2.IMAGE_ENCODING_RGB8, data=bytes(12))
    return policy_pb2.Observation(observation_id=7, arms=[arm], frames=[frame], task="pick the red cube")


def test_request_built_from_an_observation_is_the_golden_request() -> None:
    emb = Embodiment.so100(LAYOUT, camera="webcam")
    data = emb.request_data(observation_like_golden(), "main")
    assert request("get_action", data) == golden("request_get_action.msgpack")


def test_request_needs_rgb8_frames_and_known_state() -> None:
    obs = observation_like_golden()
    obs.frames[0].encoding = common_pb2.IMAGE_ENCODING_JPEG
    with pytest.raises(ObservationError, match="IMAGE_ENCODING_JPEG"):
        Embodiment.so100(LAYOUT, camera="webcam").request_data(obs, "main")
    with pytest.raises(ObservationError, match="camera 'front'"):
        Embodiment.so100(LAYOUT, camera="front").request_data(observation_like_golden(), "main")


def test_golden_answer_becomes_a_full_chunk() -> None:
    answer = unpackb(golden("response_get_action.msgpack"))
    steps = Embodiment.so100(LAYOUT, camera="webcam", action_scale=0.001).chunk_steps(answer, LAYOUT)
    assert steps.shape == (16, 7)
    expected = np.arange(80, dtype=np.float64).reshape(16, 5) * 0.001
    np.testing.assert_allclose(steps[:, :5], expected, atol=1e-9)
    assert np.all(steps[:, 5] == 0) and np.all(steps[:, 6] == 0)
    assert Embodiment.so100(LAYOUT, "webcam").chunk_steps(answer, LAYOUT, max_steps=8).shape == (8, 7)


def _answer_with(**arrays: np.ndarray) -> dict:
    return {f"action.{k}": v for k, v in arrays.items()}


def test_wrong_shapes_are_refused_with_the_shapes_named() -> None:
    emb = Embodiment.phone2act(LAYOUT)
    ok = _answer_with(arm=np.zeros((16, 6), np.float32), gripper=np.zeros((16, 1), np.float32))
    assert emb.chunk_steps(ok, LAYOUT).shape == (16, 7)
    squeezed = _answer_with(arm=np.zeros((16, 6), np.float32), gripper=np.zeros(16, np.float32))
    assert emb.chunk_steps(squeezed, LAYOUT).shape == (16, 7)
    cases = {
        "action.arm has shape (16, 5); expected (horizon, 6)":
            _answer_with(arm=np.zeros((16, 5)), gripper=np.zeros((16, 1))),
        "has horizon 8, other groups 16": _answer_with(arm=np.zeros((16, 6)), gripper=np.zeros((8, 1))),
        "has no 'action.gripper'": _answer_with(arm=np.zeros((16, 6))),
        "non-finite": _answer_with(arm=np.full((16, 6), np.nan), gripper=np.zeros((16, 1))),
    }
    for message, answer in cases.items():
        with pytest.raises(ChunkShapeError, match=message.replace("(", r"\(").replace(")", r"\)")):
            emb.chunk_steps(answer, LAYOUT)


def test_client_against_the_stand_in() -> None:
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
