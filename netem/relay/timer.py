"""How long the relay's loop may sleep: `WakeTimer` learns how late this host's timers fire.

`select` oversleeps, by ~0.1 ms plus, on some VMs, a share of the sleep itself (a guest timer
running a few per cent slow: 0.5 ms late after 10 ms). The relay sets its timer slack to 1 ns
and learns both parts, so it sleeps short of a packet's departure (at most 0.3 ms plus the
learnt share), sleeps again for what is left, and polls the last stretch; deadlines farther
away are pure sleeps, so an idle link costs no CPU. Polling has a CPU budget (10% of a core);
past it, on a busy link, a packet due within the oversleep leaves that much early instead, so
the error stays centred on zero.
"""

from __future__ import annotations

#: Bounds of the early wake-up, which tracks the measured timer oversleep. The loop polls
#: (spins) only for a packet due within the early wake-up, so never for more than the maximum.
EARLY_MIN_S, EARLY_MAX_S = 0.00002, 0.0003
#: A sleep longer than this also teaches the timer's stretch (oversleep per second asked),
#: which is capped: a host 25% slow is broken, not slow.
STRETCH_FROM_S, STRETCH_MAX = 0.001, 0.25
#: Share of a core the loop may spend polling, and the most it may save up (seconds).
SPIN_SHARE, SPIN_BURST_S = 0.1, 0.005


class WakeTimer:
    """Decides how long the loop may sleep, learning how late this host's timers fire.

    A packet due within the expected oversleep is waited for by polling (spinning), which
    makes it leave on time. Spinning is paid from a budget that refills at `spin_share` of
    a core: on a busy link, where deadlines come every few tens of µs, polling would take a
    whole core, so once the budget is spent such packets leave up to `early_s` ahead of time
    instead (`ahead_s`), which centres the timing error on zero at no CPU cost.
    """

    def __init__(self, spin_share: float = SPIN_SHARE) -> None:
        self.early_s = 0.0001  # the VM's median oversleep, refined as we go
        self.stretch = 0.0  # extra oversleep per second of sleep asked (a slow guest timer)
        self.spin_share = spin_share
        self.spin_budget_s = SPIN_BURST_S
        self.ahead_s = 0.0  # how early a packet may leave after this plan
        self.sleeps = 0
        self.spins = 0
        self.early_releases = 0
        self._last: float | None = None
        self._spinning = False

    def timeout(self, soft: float | None, hard: float | None, now: float) -> float | None:
        """Seconds to block in select (None: until an event; 0: poll).

        `hard` is when a packet leaves the link (it must be on time); `soft` is a hand-off
        between stages (exact whenever it is handled), so it never causes a spin.
        """
        if self._last is not None:
            elapsed = now - self._last
            if self._spinning:
                self.spin_budget_s -= elapsed
            self.spin_budget_s = min(SPIN_BURST_S, self.spin_budget_s + elapsed * self.spin_share)
        self._last = now
        self._spinning = False
        self.ahead_s = 0.0
        timeout: float | None = None
        if soft is not None:
            timeout = max(0.0, soft - now)
        if hard is not None:
            wait = hard - now
            if wait <= 0:
                return 0.0
            if wait <= self.early_s:
                # Due within the oversleep (always < 0.3 ms): a sleep would be late.
                if self.spin_budget_s > 0:
                    self._spinning = True
                    self.spins += 1
                else:
                    self.ahead_s = self.early_s
                    self.early_releases += 1
                return 0.0
            # Twice the learnt stretch: its wake-ups scatter about as much again, and one
            # short sleep more (for what is left) costs far less than a late packet.
            sleep = (wait - self.early_s) / (1.0 + 2.0 * self.stretch)
            if timeout is None or sleep < timeout:
                timeout = sleep
        return timeout

    def observe(self, asked: float, slept: float) -> None:
        """Feed back a sleep that ended by timeout, to track the oversleep (EWMAs).

        A short sleep's oversleep is the fixed part (`early_s`); what a long one oversleeps
        beyond that, per second asked, is the stretch.
        """
        if asked <= 0:
            return
        self.sleeps += 1
        over = max(slept - asked, 0.0)
        if asked > STRETCH_FROM_S:
            share = min(max(over - self.early_s, 0.0) / asked, STRETCH_MAX)
            self.stretch = 0.9 * self.stretch + 0.1 * share
            over -= self.stretch * asked
        over = min(max(over, 0.0), 0.002)
        early = 0.95 * self.early_s + 0.05 * over
        self.early_s = min(max(early, EARLY_MIN_S), EARLY_MAX_S)
