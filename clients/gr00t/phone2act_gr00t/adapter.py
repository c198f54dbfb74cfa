"""The adapter loop: phone2act observation -> GR00T `get_action` -> action chunk pushed to the arm.

Each chunk answers the observation it was computed from (its `observation_id`), so the server anchors it at
that observation's time and pose: inference latency skips steps already past instead of delaying the plan.
If GR00T answers late or not at all, nothing is pushed and the server's silence timeout makes the arm hold.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from phone2act import DELTA_EE, PolicySession
from phone2act.v1 import policy_pb2

from phone2act_gr00t.embodiment import Embodiment
from phone2act_gr00t.wire import Gr00tClient, Gr00tError, Gr00tTimeout

log = logging.getLogger("phone2act_gr00t")


@dataclass
class StepResult:
    observation_id: int
    steps: np.ndarray
    inference_s: float
    accepted: policy_pb2.ChunkAccepted


@dataclass
class AdapterStats:
    chunks: int = 0
    timeouts: int = 0
    errors: int = 0
    last_error: str = ""


class Gr00tAdapter:
    def __init__(
        self,
        session: PolicySession,
        gr00t: Gr00tClient,
        embodiment: Embodiment,
        *,
        arm: str = "main",
        step_period_s: float = 0.05,
        max_steps: int | None = None,
        mode: int = DELTA_EE,
    ) -> None:
        if arm not in session.layouts:
            raise ValueError(f"the policy session does not hold arm {arm!r} (it has {sorted(session.layouts)})")
        self.session = session
        self.gr00t = gr00t
        self.embodiment = embodiment
        self.arm = arm
        self.layout = session.layouts[arm]
        self.step_period_s = step_period_s
        self.max_steps = max_steps
        self.mode = mode
        self.stats = AdapterStats()

    def step(self, obs: policy_pb2.Observation | None = None) -> StepResult:
        """One inference: the newest observation (or `obs`), GR00T's answer, the chunk pushed.

        Raises Gr00tTimeout (late policy), Gr00tError (policy error), ChunkShapeError (answer does not fit the
        arm), or a phone2act error if the server refuses the chunk. Nothing is pushed when it raises.
        """
        if obs is None:
            obs = self.session.next_observation()
        data = self.embodiment.request_data(obs, self.arm)
        t0 = time.monotonic()
        answer = self.gr00t.get_action(data)
        inference_s = time.monotonic() - t0
        steps = self.embodiment.chunk_steps(answer, self.layout, self.max_steps)
        accepted = self.session.push(
            self.arm, steps, self.step_period_s, observation_id=obs.observation_id, mode=self.mode
        )
        self.stats.chunks += 1
        return StepResult(obs.observation_id, steps, inference_s, accepted)

    def run(
        self,
        *,
        max_chunks: int | None = None,
        should_stop: Callable[[], bool] = lambda: False,
        max_consecutive_failures: int = 10,
    ) -> AdapterStats:
        """Loop until `should_stop()`, `max_chunks`, the operator taking over, or too many failures in a row.

        A late or failing policy is logged and retried with a fresh observation; meanwhile the arm holds.
        """
        failures = 0
        while not should_stop() and (max_chunks is None or self.stats.chunks < max_chunks):
            if self.session.revoked is not None:
                log.warning("control revoked: %s", self.session.revoked.reason)
                break
            try:
                r = self.step()
                failures = 0
                log.info("obs %d: %d steps scheduled (%d skipped), inference %.0f ms", r.observation_id,
                         r.accepted.steps_scheduled, r.accepted.steps_skipped, r.inference_s * 1e3)
                # Ask again when about half the chunk has played (the usual receding-horizon cadence).
                time.sleep(max(0.0, 0.5 * len(r.steps) * self.step_period_s - r.inference_s))
            except (Gr00tTimeout, Gr00tError, ValueError) as e:
                failures += 1
                if isinstance(e, Gr00tTimeout):
                    self.stats.timeouts += 1
                else:
                    self.stats.errors += 1
                self.stats.last_error = str(e)
                log.error("%s; no chunk pushed, the arm holds", e)
                if failures >= max_consecutive_failures:
                    break
        return self.stats
