"""The adapter loop: phone2act observation -> GR00T `get_action` -> one action chunk per arm.

Each chunk answers the observation it was computed from (its `observation_id`), so the server anchors it at
that observation's time and pose: inference latency skips steps already past instead of delaying the plan.
Each arm's chunk is pushed in the action mode the server reports for that arm (the representation its dataset
holds, which is what the model answers in). If GR00T answers late or not at all, nothing is pushed and the
server's silence timeout makes the arm hold.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from phone2act import FailedPrecondition, Phone2ActError, PolicySession
from phone2act.v1 import policy_pb2

from phone2act_gr00t.embodiment import ChunkShapeError, Embodiment, NonFiniteActionError, ObservationError
from phone2act_gr00t.modes import action_mode_of
from phone2act_gr00t.wire import (
    CHECKED_AGAINST,
    MSGPACK_NUMPY,
    N15,
    N16,
    N16_SIM,
    N17,
    N17_SIM,
    NPY,
    WIRE_VERSIONS,
    Gr00tClient,
    Gr00tError,
    Gr00tProtocolError,
    Gr00tTimeout,
    shapes_of,
)

log = logging.getLogger("phone2act_gr00t")


class MissingTaskError(ObservationError):
    """Neither `--task` nor the server gives an instruction for the language-conditioned model."""


@dataclass
class StepResult:
    observation_id: int
    # Per arm: the rows pushed, the mode they were pushed with, and the server's answer.
    steps: dict[str, np.ndarray]
    modes: dict[str, int]
    inference_s: float
    accepted: dict[str, policy_pb2.ChunkAccepted]

    @property
    def horizon(self) -> int:
        return min(len(s) for s in self.steps.values())


@dataclass
class AdapterStats:
    chunks: int = 0
    timeouts: int = 0
    errors: int = 0
    last_error: str = ""
    per_arm: dict[str, int] = field(default_factory=dict)
    # Chunks refused because the operator had taken the arm (the policy waits for the hand-back) or answered an
    # observation from before the hand-back.
    waiting: int = 0


def waits_for_operator(error: Phone2ActError) -> bool:
    """True for the server's refusals of a policy the operator took the arm from: it waits for the hand-back, or
    its chunk answered an observation from before it (the next fresh one drives)."""
    return isinstance(error, FailedPrecondition) and (
        "hand the arm back" in error.details or "handed the arm back" in error.details
    )


# How often a waiting policy asks again (one inference each time): soon enough after a hand-back, rarely enough
# not to keep the inference server busy while the operator drives.
WAITING_RETRY_S = 0.25


class Gr00tAdapter:
    def __init__(
        self,
        session: PolicySession,
        gr00t: Gr00tClient,
        embodiment: Embodiment,
        *,
        wire: str = N15,
        task: str | None = None,
        step_period_s: float = 0.05,
        max_steps: int | None = None,
        arm_states: Mapping[str, Any] | None = None,
    ) -> None:
        missing = [a for a in embodiment.arms if a not in session.layouts]
        if missing:
            raise ValueError(f"the policy session does not hold arm(s) {missing} (it has {sorted(session.layouts)})")
        if wire not in WIRE_VERSIONS:
            raise ValueError(f"unknown GR00T wire version {wire!r} ({', '.join(WIRE_VERSIONS)})")
        self.session = session
        self.gr00t = gr00t
        self.embodiment = embodiment
        self.wire = wire
        self.task = task
        self.arms: Sequence[str] = embodiment.arms
        self.layouts = {a: session.layouts[a] for a in self.arms}
        self.step_period_s = step_period_s
        self.max_steps = max_steps
        # `System.ListArms` snapshots, for an action mode the server reports there rather than per observation.
        self.arm_states = dict(arm_states or {})
        self.stats = AdapterStats()

    def instruction(self, obs: policy_pb2.Observation) -> str:
        """`--task` if given, else the task of the episode in progress (or the server's default task)."""
        text = self.task if self.task else obs.task
        if not text.strip():
            raise MissingTaskError(
                "no task instruction: pass --task, or start an episode with a task, or configure the server's "
                "default task (GR00T is language-conditioned; an empty instruction is not a task)"
            )
        return text

    def _get_action(self, data: dict) -> object:
        try:
            return self.gr00t.get_action(data)
        except Gr00tProtocolError:
            raise
        except Gr00tError as e:
            # What each dialect's server says when handed the other dialect's request.
            if self.wire == N15 and "unexpected keyword argument" in str(e):
                raise Gr00tProtocolError(
                    f"{e}. This GR00T server speaks N1.6 ({CHECKED_AGAINST[N16]}): run with --gr00t-version n1.6 "
                    f"(or auto)"
                ) from None
            if shapes_of(self.wire) == N16 and "must be in observation" in str(e) and (
                    "'video." in str(e) or "'state." in str(e)):
                raise Gr00tProtocolError(
                    f"{e}. This GR00T server runs with --use-sim-policy-wrapper (flat keys): run with "
                    f"--gr00t-version {N17_SIM if self.wire == N17 else N16_SIM}"
                ) from None
            if "<class 'dict'>" in str(e):
                # Our arrays reached the server as plain maps: it reads the other codec.
                other = NPY if self.gr00t.codec == MSGPACK_NUMPY else MSGPACK_NUMPY
                raise Gr00tProtocolError(
                    f"{e}. This GR00T server reads arrays in the {other} codec, not {self.gr00t.codec} "
                    f"(GR00T main since 2026-05-26 uses msgpack-numpy, the n1.7-release tag and older npy): run "
                    f"with --gr00t-codec {other}"
                ) from None
            raise

    def step(self, obs: policy_pb2.Observation | None = None) -> StepResult:
        """One inference: the newest observation (or `obs`), GR00T's answer, one chunk pushed per arm.

        Raises Gr00tTimeout (late policy), Gr00tError (policy error; Gr00tProtocolError for a server this adapter
        cannot speak to), ChunkShapeError (answer does not fit an arm), ObservationError (no instruction, missing
        camera), or a phone2act error if the server refuses a chunk. Nothing is pushed when GR00T's answer is late
        or does not fit: every arm's chunk is built and checked before the first is pushed.
        """
        if obs is None:
            obs = self.session.next_observation()
        arm_obs = {a.arm: a for a in obs.arms}
        modes = {arm: action_mode_of(arm_obs[arm], self.arm_states.get(arm)) for arm in self.arms if arm in arm_obs}
        data = self.embodiment.request_data(obs, self.instruction(obs), self.wire)
        t0 = time.monotonic()
        answer = self._get_action(data)
        inference_s = time.monotonic() - t0
        steps = self.embodiment.chunk_steps(answer, self.layouts, self.max_steps, wire=self.wire, modes=modes)
        accepted = {}
        for arm, rows in steps.items():
            try:
                accepted[arm] = self.session.push(
                    arm, rows, self.step_period_s, observation_id=obs.observation_id, mode=modes[arm]
                )
            except Phone2ActError:
                if accepted:
                    # A bimanual plan half executed is not the plan: the arms already given their part hold too.
                    log.error("arm %s refused its chunk after %s accepted theirs; releasing every arm", arm,
                              sorted(accepted))
                    self.session.release()
                raise
            self.stats.per_arm[arm] = self.stats.per_arm.get(arm, 0) + 1
        self.stats.chunks += 1
        return StepResult(obs.observation_id, steps, modes, inference_s, accepted)

    def run(
        self,
        *,
        max_chunks: int | None = None,
        should_stop: Callable[[], bool] = lambda: False,
        max_consecutive_failures: int = 10,
    ) -> AdapterStats:
        """Loop until `should_stop()`, `max_chunks`, control revoked, or too many failures in a row.

        When the operator takes an arm with the phone the session waits: its chunks are refused (counted in
        `stats.waiting`) and the loop keeps observing, so that the operator's hand-back lets the next chunk, which
        answers a fresh observation, drive again.

        A late or failing policy is logged and retried with a fresh observation; meanwhile the arm holds. A server
        that speaks another wire format (Gr00tProtocolError), an answer whose shape does not fit the arm
        (ChunkShapeError: the model's shape is the same at every step) or a missing instruction stops the loop at
        once: retrying cannot fix any of them. An answer holding NaN is a bad answer and is retried.
        """
        failures = 0
        while not should_stop() and (max_chunks is None or self.stats.chunks < max_chunks):
            if self.session.revoked is not None:
                log.warning("control revoked: %s", self.session.revoked.reason)
                break
            try:
                r = self.step()
                failures = 0
                for arm, acc in r.accepted.items():
                    log.info("obs %d %s: %d steps scheduled (%d skipped), inference %.0f ms", r.observation_id, arm,
                             acc.steps_scheduled, acc.steps_skipped, r.inference_s * 1e3)
                # Ask again when about half the chunk has played (the usual receding-horizon cadence).
                time.sleep(max(0.0, 0.5 * r.horizon * self.step_period_s - r.inference_s))
            except Phone2ActError as e:
                if not waits_for_operator(e):
                    raise
                self.stats.waiting += 1
                log.info("%s; asking again in %.1f s", e.details, WAITING_RETRY_S)
                time.sleep(WAITING_RETRY_S)
            except Gr00tProtocolError as e:
                self.stats.errors += 1
                self.stats.last_error = str(e)
                raise
            except ChunkShapeError as e:
                if isinstance(e, NonFiniteActionError):
                    failures += 1
                    self.stats.errors += 1
                    self.stats.last_error = str(e)
                    log.error("%s; no chunk pushed, the arm holds", e)
                    if failures >= max_consecutive_failures:
                        break
                    continue
                self.stats.errors += 1
                self.stats.last_error = str(e)
                raise
            except (Gr00tTimeout, Gr00tError, ValueError) as e:
                failures += 1
                if isinstance(e, Gr00tTimeout):
                    self.stats.timeouts += 1
                else:
                    self.stats.errors += 1
                self.stats.last_error = str(e)
                log.error("%s; no chunk pushed, the arm holds", e)
                if isinstance(e, MissingTaskError):
                    break
                if failures >= max_consecutive_failures:
                    break
        return self.stats
