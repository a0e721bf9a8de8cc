"""Loss gates: independent loss per wire packet (`RandomLoss`, netem's `loss`) and bursty
loss from a good/bad Markov chain (`GilbertElliottLoss`, netem's `loss gemodel`)."""

from __future__ import annotations

import math
import random
from typing import Any

from netem.profile import LinkProfile
from netem.stages.gates import Gate


class RandomLoss(Gate):
    """Drops each wire packet independently with probability `loss`.

    Instead of a draw per packet it draws how many packets pass before the next loss (a
    geometric number, which is the same process), so a super-packet costs one comparison.
    """

    name = "loss"

    def __init__(self, loss: float = 0.0, seed: int | str = 0) -> None:
        super().__init__()
        self._rng = random.Random(f"{seed}:{self.name}")
        self.loss = 0.0
        self._skip = 0  # wire packets that pass before the next loss
        self._set(loss)

    def _set(self, loss: float) -> None:
        if loss != self.loss:
            self.loss = loss
            self._skip = self._gap()  # memoryless: a fresh draw is as good as the old one

    def _gap(self) -> int:
        p = self.loss
        if p <= 0.0 or p >= 1.0:  # (no loss: never asked; certain loss: no gaps)
            return 0
        # P(gap = k) = (1-p)^k p; 1 - random() is in (0, 1], so the log is finite.
        return int(math.log(1.0 - self._rng.random()) / math.log1p(-p))

    def configure(self, profile: LinkProfile) -> None:
        # A Gilbert-Elliott model replaces the independent loss (netem's `loss gemodel`).
        self._set(0.0 if profile.gilbert_elliott is not None else profile.loss)

    def losses(self, n: int) -> list[int]:
        if self.loss <= 0.0:
            return []
        if self._skip >= n:
            self._skip -= n
            return []
        out: list[int] = []
        i = self._skip
        while i < n:
            out.append(i)
            i += 1 + self._gap()
        self._skip = i - n
        return out


class GilbertElliottLoss(Gate):
    """Bursty loss: a good/bad Markov chain stepped once per packet (netem's gemodel)."""

    name = "burst_loss"

    def __init__(self, model: Any = None, seed: int | str = 0) -> None:
        super().__init__()
        self.model = model
        self.bad = False
        self._rng = random.Random(f"{seed}:{self.name}")

    def configure(self, profile: LinkProfile) -> None:
        self.model = profile.gilbert_elliott
        if self.model is None:
            self.bad = False

    def losses(self, n: int) -> list[int]:
        m = self.model
        if m is None:
            return []
        rng = self._rng
        out: list[int] = []
        bad = self.bad
        for i in range(n):
            if rng.random() < (m.bad_loss if bad else m.good_loss):
                out.append(i)
            # Step the chain after deciding, so the first packet sees the good state.
            if bad:
                if rng.random() < m.r:
                    bad = False
            elif rng.random() < m.p:
                bad = True
        self.bad = bad
        return out
