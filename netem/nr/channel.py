"""A UE's radio channel from geometry: path loss, LOS state, shadowing, SINR, CQI, MCS, BLER.

Pure computation (no clock, no packets; only `RadioTrace.load` reads a file): a route's
positions go in, the radio a link would have at each of them comes out, ready to set a
`netem.nr.radio.Radio`'s `mcs` and `bler`. Everything random is seeded, so the same seed and the
same positions give the same samples.

Nouns:
- `Site`: one gNB cell, where it stands (world frame, metres), its antenna height, transmit
  power, carrier and channel bandwidth.
- `Channel`: one UE's links to every site under one TR 38.901 scenario (UMa or UMi-Street
  Canyon). `step(t, x, y, serving)` moves the UE and returns a `RadioSample`: the RSRP of
  every site, the serving cell's SINR against the others (interference) and thermal noise,
  the CQI that SINR reports, the MCS link adaptation picks for it and that MCS's BLER; and
  the same for the uplink (the UE's power at the serving gNB against the gNB's noise).
- `RadioSample`: one step's result (frozen).
- `Gudmundson`: one log-normal shadowing process, exponentially correlated in the distance
  travelled (one per UE, site and LOS state).
- `RadioTrace`: recorded radio samples (`time_s,ue,rsrp_dbm,sinr_db,mcs[,cell]`) per UE, for
  a run that replays a measured drive instead of modelling one.

The free functions (`path_loss_db`, `los_probability`, `cqi_from_sinr`, `mcs_from_cqi`,
`bler`, ...) are the model's pieces, each one formula of the spec it cites.
"""

from __future__ import annotations

import itertools
import math
import random
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Literal

from netem.errors import NetemError
from netem.nr.phy import MCS_TABLE_1, SUBCARRIERS_PER_PRB

Model = Literal["uma", "umi"]
LOS_MODES: tuple[str, ...] = ("los", "nlos", "auto")

#: Speed of light as TR 38.901 Table 7.4.1-1 note 1 takes it for the breakpoint distance.
C_M_PER_S = 3.0e8
#: Effective environment height h_E (TR 38.901 Table 7.4.1-1 note 1). For UMi it is 1 m. For
#: UMa it is 1 m with probability 1/(1 + C(d2D, hUT)), and C = 0 for hUT < 13 m, so a car's
#: or a pedestrian's UE has h_E = 1 m exactly; for a UE at 13 m or higher the spec sometimes
#: draws a larger h_E (12, 15, ... m), which this model leaves out (h_E = 1 m always).
H_E_M = 1.0
#: TR 38.901 Table 7.4.1-1: the path-loss formulas hold for 10 m <= d2D <= 5 km. Closer, the
#: log-distance law would run to a pole under the mast, so d2D is held at 10 m; beyond 5 km the
#: formulas are extrapolated (such a cell only adds a little interference).
MIN_D2D_M = 10.0
#: TR 38.901 Table 7.4.1-1: UE heights the UMa and UMi formulas are fitted for.
UE_HEIGHT_RANGE_M = (1.5, 22.5)
#: FR1 (TS 38.104 Table 5.1-1 ends at 7.125 GHz) from TR 38.901's lowest frequency, 0.5 GHz:
#: the 30 kHz PRB counts below (`N_PRB_30KHZ`) are FR1's.
CARRIER_RANGE_GHZ = (0.5, 7.125)
#: Thermal noise density at 290 K, kT, in dBm/Hz.
THERMAL_DBM_PER_HZ = -174.0
#: TS 38.101-1 Table 5.3.2-1: PRBs of an FR1 channel at 30 kHz subcarrier spacing, by channel
#: bandwidth in MHz. Band n78 (3.3-3.8 GHz, TS 38.101-1 Table 5.2-1) uses 30 kHz.
N_PRB_30KHZ: dict[int, int] = {
    5: 11, 10: 24, 15: 38, 20: 51, 25: 65, 30: 78, 40: 106, 50: 133, 60: 162, 70: 189, 80: 217,
    90: 245, 100: 273,
}  # fmt: skip

#: TS 38.214 Table 5.2.2.1-2 (4-bit CQI table 1, up to 64QAM): (Qm, code rate x 1024) of
#: CQI 1..15 (CQI 0 is "out of range"). It is the same table as LTE's (TS 36.213 7.2.3-1).
CQI_TABLE_1: tuple[tuple[int, int], ...] = (
    (2, 78), (2, 120), (2, 193), (2, 308), (2, 449), (2, 602), (4, 378), (4, 490), (4, 616),
    (6, 466), (6, 567), (6, 666), (6, 772), (6, 873), (6, 948),
)  # fmt: skip
#: The SINR (dB) at which each CQI 1..15 decodes at 10% BLER: an assumption, not a 3GPP
#: table. These are the AWGN thresholds widely used for the LTE/NR CQI table 1 in system-level
#: simulation (a UE reports the highest CQI whose threshold its SINR reaches, as TS 38.214
#: §5.2.2.1 defines CQI by a 10% transport-block error target); a real UE's mapping depends on
#: its receiver and the channel's fading.
CQI_SINR_DB: tuple[float, ...] = (
    -6.7, -4.7, -2.3, 0.2, 2.4, 4.3, 5.9, 8.1, 10.3, 11.7, 14.1, 16.3, 18.7, 21.0, 22.7,
)  # fmt: skip
#: BLER target that defines CQI (TS 38.214 §5.2.2.1) and so the thresholds above.
TARGET_BLER = 0.1
#: Steepness of the BLER curve around an MCS's threshold, per dB (an assumption): BLER goes
#: from 90% to 1% over ~3.4 dB, the width of an AWGN curve of a long LDPC-coded block.
BLER_SLOPE_PER_DB = 2.0
#: A UE's maximum output power: power class 3, 23 dBm (TS 38.101-1 Table 6.2.1-1), the class
#: of phones and of most vehicle modems.
UE_POWER_DBM = 23.0
#: UE and gNB noise figures of 3GPP's system-level evaluations below 6 GHz: 9 dB and 5 dB
#: (TR 36.814 Table A.2.1.1-2 for the UE; TR 38.802 Table A.2.1-1 and ITU-R M.2412 for the BS).
UE_NOISE_FIGURE_DB = 9.0
GNB_NOISE_FIGURE_DB = 5.0


class ChannelError(NetemError, ValueError):
    """A site, a channel setting or a position the model cannot take; the message says which."""


@dataclass(frozen=True)
class _Scenario:
    """What differs between TR 38.901's scenarios, apart from the path-loss formulas."""

    sigma_los_db: float  # Table 7.4.1-1, shadow fading std
    sigma_nlos_db: float
    decorrelation_los_m: float  # Table 7.5-6 part-1, SF correlation distance
    decorrelation_nlos_m: float
    los_state_m: float  # Table 7.6.3.1-2, correlation distance of the LOS/NLOS state


_SCENARIOS: dict[str, _Scenario] = {
    "uma": _Scenario(4.0, 6.0, 37.0, 50.0, 50.0),
    "umi": _Scenario(4.0, 7.82, 10.0, 13.0, 50.0),
}
#: The scenarios a `Channel` knows: TR 38.901 UMa and UMi-Street Canyon.
MODELS: tuple[str, ...] = tuple(_SCENARIOS)


def _scenario(model: str) -> _Scenario:
    if model not in _SCENARIOS:
        raise ChannelError(f"unknown model {model!r} (known: {', '.join(MODELS)})")
    return _SCENARIOS[model]


@dataclass(frozen=True)
class Site:
    """One gNB cell: position (m, world frame), antenna height, power, carrier, bandwidth.

    `tx_power_dbm` is the total over the channel. 46 dBm (40 W) is the macro-cell power of
    3GPP's system-level evaluation assumptions (TR 36.814 Table A.2.1.1-2, there for 10 MHz):
    an assumption for NR, where a 100 MHz n78 macro radiates more. With every cell at the same
    power only the noise-limited cell edge depends on it, since interference scales with it
    too. Antennas are isotropic (0 dBi, no sectors or beams). The defaults are a 3.5 GHz,
    100 MHz carrier in band n78 at 30 kHz (273 PRBs, TS 38.101-1 Table 5.3.2-1) on a 25 m mast,
    TR 38.901's UMa base station height.
    """

    name: str
    x: float
    y: float
    height_m: float = 25.0
    tx_power_dbm: float = 46.0
    carrier_ghz: float = 3.5
    bandwidth_mhz: int = 100

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ChannelError(f"a site needs a name, got {self.name!r}")
        where = f"site {self.name}"
        for field in ("x", "y", "height_m", "tx_power_dbm", "carrier_ghz"):
            value = getattr(self, field)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ChannelError(f"{where}: {field} must be a finite number, got {value!r}")
        if self.height_m <= 0:
            raise ChannelError(f"{where}: height_m must be > 0 m, got {self.height_m:g}")
        if not -10.0 <= self.tx_power_dbm <= 70.0:
            raise ChannelError(
                f"{where}: tx_power_dbm must be -10..70 dBm, got {self.tx_power_dbm:g}"
            )
        low, high = CARRIER_RANGE_GHZ
        if not low <= self.carrier_ghz <= high:
            raise ChannelError(
                f"{where}: carrier_ghz must be {low:g}..{high:g} GHz (FR1 within TR 38.901's "
                f"range), got {self.carrier_ghz:g}"
            )
        if self.bandwidth_mhz not in N_PRB_30KHZ:
            allowed = ", ".join(map(str, N_PRB_30KHZ))
            raise ChannelError(
                f"{where}: bandwidth_mhz must be one of {allowed} (TS 38.101-1 Table "
                f"5.3.2-1 at 30 kHz), got {self.bandwidth_mhz!r}"
            )

    @property
    def n_prb(self) -> int:
        return N_PRB_30KHZ[self.bandwidth_mhz]

    @property
    def re_per_symbol(self) -> int:
        """Resource elements one OFDM symbol spreads the transmit power over."""
        return SUBCARRIERS_PER_PRB * self.n_prb


def breakpoint_m(h_bs_m: float, h_ut_m: float, fc_ghz: float) -> float:
    """d'_BP = 4 h'_BS h'_UT f_c / c with h' = h - h_E (TR 38.901 Table 7.4.1-1 note 1)."""
    return 4.0 * (h_bs_m - H_E_M) * (h_ut_m - H_E_M) * fc_ghz * 1e9 / C_M_PER_S


def path_loss_db(
    model: str, los: bool, d2d_m: float, h_bs_m: float, h_ut_m: float, fc_ghz: float
) -> float:
    """Path loss in dB per TR 38.901 Table 7.4.1-1 (distances in m, f_c in GHz).

    LOS is the two-slope model around the breakpoint d'_BP; NLOS is max(LOS, NLOS'), as the
    table writes it, so NLOS is never below LOS. d2D below 10 m is taken as 10 m (`MIN_D2D_M`).
    """
    _scenario(model)
    d2d = max(d2d_m, MIN_D2D_M)
    dh = h_bs_m - h_ut_m
    d3d = math.hypot(d2d, dh)
    d_bp = breakpoint_m(h_bs_m, h_ut_m, fc_ghz)
    lf = math.log10(fc_ghz)
    if model == "uma":
        if d2d <= d_bp:
            pl_los = 28.0 + 22.0 * math.log10(d3d) + 20.0 * lf
        else:
            pl_los = 28.0 + 40.0 * math.log10(d3d) + 20.0 * lf - 9.0 * math.log10(d_bp**2 + dh**2)
        if los:
            return pl_los
        pl_nlos = 13.54 + 39.08 * math.log10(d3d) + 20.0 * lf - 0.6 * (h_ut_m - 1.5)
        return max(pl_los, pl_nlos)
    if d2d <= d_bp:
        pl_los = 32.4 + 21.0 * math.log10(d3d) + 20.0 * lf
    else:
        pl_los = 32.4 + 40.0 * math.log10(d3d) + 20.0 * lf - 9.5 * math.log10(d_bp**2 + dh**2)
    if los:
        return pl_los
    pl_nlos = 22.4 + 35.3 * math.log10(d3d) + 21.3 * lf - 0.3 * (h_ut_m - 1.5)
    return max(pl_los, pl_nlos)


def los_probability(model: str, d2d_m: float, h_ut_m: float = 1.5) -> float:
    """Probability of line of sight at d2D (outdoor UE), TR 38.901 Table 7.4.2-1."""
    _scenario(model)
    if d2d_m <= 18.0:
        return 1.0
    base_scale = 63.0 if model == "uma" else 36.0
    p = 18.0 / d2d_m + math.exp(-d2d_m / base_scale) * (1.0 - 18.0 / d2d_m)
    if model == "uma" and h_ut_m > 13.0:
        # C'(hUT) for a UE between 13 and 23 m (a balcony, a drone); 0 at or below 13 m.
        c = ((h_ut_m - 13.0) / 10.0) ** 1.5
        p *= 1.0 + c * 1.25 * (d2d_m / 100.0) ** 3 * math.exp(-d2d_m / 150.0)
    return min(1.0, p)


def thermal_noise_dbm(bandwidth_hz: float, noise_figure_db: float) -> float:
    """Receiver noise over a bandwidth: kT (-174 dBm/Hz) + 10 log10(B) + NF."""
    return THERMAL_DBM_PER_HZ + 10.0 * math.log10(bandwidth_hz) + noise_figure_db


def _efficiency_x1024(qm: int, rate_x1024: int) -> int:
    """Bits per resource element x 1024, kept an integer so equal table entries compare equal."""
    return qm * rate_x1024


def cqi_from_sinr(sinr_db: float) -> int:
    """The CQI a UE reports at this SINR: the highest whose threshold it reaches (0: none)."""
    cqi = 0
    for index, threshold in enumerate(CQI_SINR_DB, start=1):
        if sinr_db >= threshold:
            cqi = index
    return cqi


def mcs_from_cqi(cqi: int) -> int:
    """Link adaptation: the MCS of TS 38.214 Table 5.1.3.1-1 with the highest spectral
    efficiency not above CQI `cqi`'s (Table 5.2.2.1-2).

    CQI 0 (out of range) and CQI 1, whose efficiency is below every MCS's, get MCS 0: a gNB
    keeps scheduling at its most robust MCS rather than not at all.
    """
    if not 0 <= cqi <= len(CQI_TABLE_1):
        raise ChannelError(f"cqi must be 0..{len(CQI_TABLE_1)} (TS 38.214 Table 5.2.2.1-2)")
    if cqi == 0:
        return 0
    target = _efficiency_x1024(*CQI_TABLE_1[cqi - 1])
    fitting = [
        (_efficiency_x1024(qm, rate), mcs)
        for mcs, (qm, rate) in enumerate(MCS_TABLE_1)
        if _efficiency_x1024(qm, rate) <= target
    ]
    # Table 5.1.3.1-1 is not monotone in efficiency (MCS 17 carries less than MCS 16), hence
    # the largest efficiency rather than the largest index.
    return max(fitting)[1] if fitting else 0


def mcs_threshold_db(mcs: int) -> float:
    """The SINR at which `mcs` decodes at 10% BLER: `CQI_SINR_DB` interpolated linearly in
    spectral efficiency between the CQIs around the MCS (an MCS with a CQI's efficiency gets
    that CQI's threshold exactly)."""
    if not 0 <= mcs < len(MCS_TABLE_1):
        raise ChannelError(f"mcs must be 0..{len(MCS_TABLE_1) - 1} (TS 38.214 Table 5.1.3.1-1)")
    eff = _efficiency_x1024(*MCS_TABLE_1[mcs])
    points = [
        (_efficiency_x1024(qm, r), thr)
        for (qm, r), thr in zip(CQI_TABLE_1, CQI_SINR_DB, strict=True)
    ]
    if eff <= points[0][0]:
        return points[0][1]
    for (e0, t0), (e1, t1) in itertools.pairwise(points):
        if eff <= e1:
            return t0 + (t1 - t0) * (eff - e0) / (e1 - e0)
    return points[-1][1]


def bler(mcs: int, sinr_db: float, slope_per_db: float = BLER_SLOPE_PER_DB) -> float:
    """First-transmission BLER of `mcs` at `sinr_db`: a logistic curve in dB, 10% at the MCS's
    threshold (`mcs_threshold_db`), falling with `slope_per_db`.

    A simplification: a real curve depends on the block length, the channel's fading and the
    receiver; this one only keeps its place (10% at the threshold) and a plausible width.
    """
    # 1 / (1 + 9 e^x) is 0.1 at x = 0; written so that neither branch can overflow.
    x = slope_per_db * (sinr_db - mcs_threshold_db(mcs))
    odds = (1.0 - TARGET_BLER) / TARGET_BLER
    if x >= 0.0:
        e = math.exp(-x)
        return e / (e + odds)
    return 1.0 / (1.0 + odds * math.exp(x))


class Gudmundson:
    """A log-normal shadowing process (dB) along a route, exponentially correlated in distance.

    Gudmundson's model (Electron. Lett. 27(23), 1991): the correlation of two values d metres
    apart is exp(-d / d_corr). Sampled along the distance travelled it is an AR(1):
    s' = rho s + sigma sqrt(1 - rho^2) w, rho = exp(-moved / d_corr), w ~ N(0, 1), which keeps
    the variance sigma^2 at any step length. The correlation follows the route, not a map: a UE
    that comes back to a place finds a fresh value there.
    """

    def __init__(self, sigma_db: float, decorrelation_m: float, rng: random.Random) -> None:
        if sigma_db < 0 or decorrelation_m <= 0:
            raise ChannelError(
                f"shadowing needs sigma >= 0 dB and a decorrelation distance > 0 m, got "
                f"{sigma_db:g} dB and {decorrelation_m:g} m"
            )
        self.sigma_db = sigma_db
        self.decorrelation_m = decorrelation_m
        self._rng = rng
        self.value_db = sigma_db * rng.gauss(0.0, 1.0)

    def advance(self, moved_m: float) -> float:
        """Move `moved_m` metres along the route; the shadowing there, in dB."""
        rho = math.exp(-max(0.0, moved_m) / self.decorrelation_m)
        # One draw per step whatever the distance, so the stream stays aligned with the steps.
        w = self._rng.gauss(0.0, 1.0)
        self.value_db = rho * self.value_db + self.sigma_db * math.sqrt(1.0 - rho * rho) * w
        return self.value_db


class _LosField:
    """A spatially consistent uniform variable along the route for the LOS state.

    TR 38.901 §7.6.3.3 draws the LOS state by comparing such a variable with the LOS
    probability. Its Gaussian is drawn at knots one correlation distance (Table 7.6.3.1-2)
    apart, correlated e^-1 between neighbours, and interpolated between them (rescaled to unit
    variance, so the marginal is exactly N(0, 1) and the uniform exactly uniform). Unlike an
    AR(1) step by step, whose path is rough, the interpolated path crosses a threshold at most
    a few times per knot interval: the state does not flicker while the UE creeps along a
    boundary.
    """

    RHO = math.exp(-1.0)

    def __init__(self, spacing_m: float, rng: random.Random) -> None:
        self.spacing_m = spacing_m
        self._rng = rng
        self._a = rng.gauss(0.0, 1.0)
        self._b = self._next(self._a)
        self._offset_m = 0.0

    def _next(self, previous: float) -> float:
        return self.RHO * previous + math.sqrt(1.0 - self.RHO**2) * self._rng.gauss(0.0, 1.0)

    def advance(self, moved_m: float) -> float:
        """Move `moved_m` metres; the uniform variable (0..1) there."""
        self._offset_m += max(0.0, moved_m)
        knots = math.floor(self._offset_m / self.spacing_m)
        if knots > 32:
            # e^-32 of correlation left: start afresh rather than walk every knot of a jump.
            self._a = self._rng.gauss(0.0, 1.0)
            self._b = self._next(self._a)
        else:
            for _ in range(knots):
                self._a, self._b = self._b, self._next(self._b)
        self._offset_m -= knots * self.spacing_m
        w = self._offset_m / self.spacing_m
        spread = math.sqrt((1 - w) ** 2 + w**2 + 2 * w * (1 - w) * self.RHO)
        g = ((1 - w) * self._a + w * self._b) / spread
        return 0.5 * (1.0 + math.erf(g / math.sqrt(2.0)))


@dataclass(frozen=True)
class RadioSample:
    """One step of a `Channel`: where the UE was, what it received, what the link runs at.

    `rsrp_dbm` and `los` have one entry per site; `sinr_db`, `cqi`, `mcs` and `bler` are the
    serving cell's downlink (`mcs` and `bler` are what a `netem.nr.radio.Radio` takes), the `ul_`
    fields its uplink's.
    """

    t: float
    x: float
    y: float
    serving: str
    rsrp_dbm: Mapping[str, float]
    los: Mapping[str, bool]
    sinr_db: float
    cqi: int
    mcs: int
    bler: float
    ul_sinr_db: float
    ul_cqi: int
    ul_mcs: int
    ul_bler: float

    @property
    def strongest(self) -> str:
        """The site with the highest RSRP (the first in site order on a tie)."""
        return max(self.rsrp_dbm, key=lambda name: self.rsrp_dbm[name])


class _Link:
    """The random state of one UE-site link: the LOS-state field and a shadowing process for
    each state (TR 38.901 draws the LOS and NLOS large-scale parameters independently)."""

    def __init__(self, site: Site, scenario: _Scenario, seed: int, ue: str) -> None:
        self.site = site

        def rng(stream: str) -> random.Random:
            # A string seed is hashed with SHA-512 by `random`, so streams are stable across
            # runs and independent per (seed, UE, site, stream) whatever the order of the sites.
            return random.Random(f"{seed}/{ue}/{site.name}/{stream}")

        self.los_field = _LosField(scenario.los_state_m, rng("los-state"))
        self.shadow_los = Gudmundson(
            scenario.sigma_los_db, scenario.decorrelation_los_m, rng("sf-los")
        )
        self.shadow_nlos = Gudmundson(
            scenario.sigma_nlos_db, scenario.decorrelation_nlos_m, rng("sf-nlos")
        )


class Channel:
    """One UE's radio towards a set of sites, step by step along its route.

    Each `step` moves the UE to (x, y) and, for every site: updates the link's LOS state
    (`los` "auto": TR 38.901 §7.6.3.3 with Table 7.4.2-1's probability; or forced "los" /
    "nlos") and its shadowing (`Gudmundson`, sigma from Table 7.4.1-1, decorrelation distance
    from Table 7.5-6 part-1), then computes the RSRP, the power per resource element:
    tx power - 10 log10(12 N_PRB) - path loss - shadowing.

    The serving cell's SINR counts every other site on the same carrier as interference at
    full load (each of them sends on every resource element, the worst case and the usual
    system-level assumption), plus thermal noise over the serving channel's bandwidth with
    the UE's noise figure (`UE_NOISE_FIGURE_DB`). The SINR gives the CQI (`cqi_from_sinr`),
    the CQI the MCS (`mcs_from_cqi`), and the MCS and SINR the BLER (`bler`).

    The uplink: the UE sends `ue_power_dbm` spread over the serving channel's resource
    elements (it is given the whole carrier when it sends; the cell shares it in time), over
    the same path loss and shadowing (reciprocity), against the gNB's noise
    (`GNB_NOISE_FIGURE_DB`). Other cells' UEs are not modelled, so the uplink is noise-limited:
    an optimistic uplink wherever neighbours are loaded. The uplink MCS follows from its SINR
    through the same tables (a gNB picks it from SRS measurements, not a CQI report).

    The random state advances by the distance moved since the previous step, so the samples
    depend only on the seed, the UE's name and the sequence of positions, not on the times.
    """

    def __init__(
        self,
        sites: Sequence[Site],
        model: str = "uma",
        los: str = "auto",
        seed: int = 0,
        ue: str = "ue",
        ue_height_m: float = 1.5,
        noise_figure_db: float = UE_NOISE_FIGURE_DB,
        shadowing: bool = True,
        bler_slope_per_db: float = BLER_SLOPE_PER_DB,
        ue_power_dbm: float = UE_POWER_DBM,
        gnb_noise_figure_db: float = GNB_NOISE_FIGURE_DB,
    ) -> None:
        self._scenario = _scenario(model)
        if los not in LOS_MODES:
            raise ChannelError(f"unknown los mode {los!r} (known: {', '.join(LOS_MODES)})")
        if not sites:
            raise ChannelError("a channel needs at least one site")
        low, high = UE_HEIGHT_RANGE_M
        if not low <= ue_height_m <= high:
            raise ChannelError(
                f"ue_height_m must be {low:g}..{high:g} m (TR 38.901 Table 7.4.1-1), "
                f"got {ue_height_m:g}"
            )
        for name, value in (
            ("noise_figure_db", noise_figure_db),
            ("gnb_noise_figure_db", gnb_noise_figure_db),
        ):
            if not 0.0 <= value <= 30.0:
                raise ChannelError(f"{name} must be 0..30 dB, got {value:g}")
        if not -40.0 <= ue_power_dbm <= 40.0:
            raise ChannelError(f"ue_power_dbm must be -40..40 dBm, got {ue_power_dbm:g}")
        if bler_slope_per_db <= 0:
            raise ChannelError(f"bler_slope_per_db must be > 0, got {bler_slope_per_db:g}")
        seen: dict[str, Site] = {}
        for site in sites:
            if site.name in seen:
                raise ChannelError(f"two sites are named {site.name!r}")
            for other in seen.values():
                if (other.x, other.y) == (site.x, site.y):
                    raise ChannelError(f"sites {other.name} and {site.name} are at the same place")
            if site.height_m <= ue_height_m:
                raise ChannelError(
                    f"site {site.name} ({site.height_m:g} m) must stand higher than the UE "
                    f"({ue_height_m:g} m): TR 38.901's UMa and UMi put the base station above "
                    f"the street"
                )
            seen[site.name] = site
        self.sites: tuple[Site, ...] = tuple(sites)
        self.model = model
        self.los_mode = los
        self.seed = seed
        self.ue = ue
        self.ue_height_m = ue_height_m
        self.noise_figure_db = noise_figure_db
        self.gnb_noise_figure_db = gnb_noise_figure_db
        self.ue_power_dbm = ue_power_dbm
        self.shadowing = shadowing
        self.bler_slope_per_db = bler_slope_per_db
        self._links = {site.name: _Link(site, self._scenario, seed, ue) for site in sites}
        self._last: tuple[float, float, float] | None = None

    def site(self, name: str) -> Site:
        if name not in self._links:
            known = ", ".join(self._links)
            raise ChannelError(f"no site named {name!r} (sites: {known})")
        return self._links[name].site

    def path_loss_db(self, site: str, x: float, y: float, los: bool) -> float:
        """The deterministic path loss from `site` to a UE at (x, y)."""
        s = self.site(site)
        d2d = math.hypot(x - s.x, y - s.y)
        return path_loss_db(self.model, los, d2d, s.height_m, self.ue_height_m, s.carrier_ghz)

    def step(self, t: float, x: float, y: float, serving: str) -> RadioSample:
        """Move the UE to (x, y) at time `t` (not before the previous step's) and sample."""
        serving_site = self.site(serving)
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(t)):
            raise ChannelError(f"position and time must be finite, got t={t} x={x} y={y}")
        if self._last is not None and t < self._last[0]:
            raise ChannelError(f"time went back: step at {t:g} s after one at {self._last[0]:g} s")
        moved = 0.0 if self._last is None else math.hypot(x - self._last[1], y - self._last[2])
        self._last = (t, x, y)
        rsrp: dict[str, float] = {}
        los: dict[str, bool] = {}
        loss: dict[str, float] = {}  # path loss + shadowing, the same both ways
        for name, link in self._links.items():
            s = link.site
            d2d = math.hypot(x - s.x, y - s.y)
            # Every process advances on every step, used or not, so that a forced LOS mode or
            # shadowing turned off leaves the other streams where they would have been.
            u = link.los_field.advance(moved)
            sf_los = link.shadow_los.advance(moved)
            sf_nlos = link.shadow_nlos.advance(moved)
            if self.los_mode == "auto":
                in_los = u < los_probability(self.model, d2d, self.ue_height_m)
            else:
                in_los = self.los_mode == "los"
            pl = path_loss_db(self.model, in_los, d2d, s.height_m, self.ue_height_m, s.carrier_ghz)
            sf = (sf_los if in_los else sf_nlos) if self.shadowing else 0.0
            loss[name] = pl + sf
            rsrp[name] = s.tx_power_dbm - 10.0 * math.log10(s.re_per_symbol) - pl - sf
            los[name] = in_los
        # Per resource element: the serving cell's RSRP against the neighbours' (on the same
        # carrier) and the noise of one resource element's share of the channel.
        re_db = 10.0 * math.log10(serving_site.re_per_symbol)
        bandwidth_hz = serving_site.bandwidth_mhz * 1e6
        noise_re_mw = 10.0 ** ((thermal_noise_dbm(bandwidth_hz, self.noise_figure_db) - re_db) / 10)
        interference_mw = sum(
            10.0 ** (rsrp[name] / 10.0)
            for name, link in self._links.items()
            if name != serving and math.isclose(link.site.carrier_ghz, serving_site.carrier_ghz)
        )
        sinr_db = rsrp[serving] - 10.0 * math.log10(interference_mw + noise_re_mw)
        cqi = cqi_from_sinr(sinr_db)
        mcs = mcs_from_cqi(cqi)
        # Per resource element the UE's power and the gNB's noise both take the same share of
        # the carrier, so the uplink SNR is the whole carrier's.
        ul_sinr_db = (
            self.ue_power_dbm
            - loss[serving]
            - thermal_noise_dbm(bandwidth_hz, self.gnb_noise_figure_db)
        )
        ul_cqi = cqi_from_sinr(ul_sinr_db)
        ul_mcs = mcs_from_cqi(ul_cqi)
        return RadioSample(
            t=t,
            x=x,
            y=y,
            serving=serving,
            rsrp_dbm=MappingProxyType(rsrp),
            los=MappingProxyType(los),
            sinr_db=sinr_db,
            cqi=cqi,
            mcs=mcs,
            bler=bler(mcs, sinr_db, self.bler_slope_per_db),
            ul_sinr_db=ul_sinr_db,
            ul_cqi=ul_cqi,
            ul_mcs=ul_mcs,
            ul_bler=bler(ul_mcs, ul_sinr_db, self.bler_slope_per_db),
        )


# --- recorded traces -----------------------------------------------------------------------

#: The columns of a radio trace, in order; `cell` may follow them.
TRACE_COLUMNS: tuple[str, ...] = ("time_s", "ue", "rsrp_dbm", "sinr_db", "mcs")
#: What a UE can report (TS 38.133 §10.1, the SS-RSRP and SS-SINR report mappings): a value
#: outside these is a unit mistake or a broken recording, not a radio.
RSRP_RANGE_DBM = (-156.0, -31.0)
SINR_RANGE_DB = (-23.0, 40.0)
#: Wrong lines a trace error lists before it says how many more there were.
MAX_TRACE_PROBLEMS = 5


class RadioTraceError(ChannelError):
    """A radio trace that cannot be used; `problems` holds one `file:line: field: what` each."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = tuple(problems)
        super().__init__("\n".join(self.problems))


@dataclass(frozen=True)
class TraceSample:
    """One recorded sample of one UE: time, RSRP, SINR, MCS and, if recorded, the cell."""

    t: float
    rsrp_dbm: float
    sinr_db: float
    mcs: int
    cell: str | None = None


@dataclass(frozen=True)
class RadioTrace:
    """Recorded radio samples per UE, each UE's in time order."""

    samples: Mapping[str, tuple[TraceSample, ...]]
    source: str = ""

    @property
    def ues(self) -> tuple[str, ...]:
        return tuple(self.samples)

    def at(self, ue: str, t: float) -> TraceSample | None:
        """The sample in force at `t`: the last one at or before it (None before the first)."""
        if ue not in self.samples:
            raise ChannelError(
                f"{self.source}: no UE {ue!r} in the trace (UEs: {', '.join(self.ues)})"
            )
        found = None
        lo, hi = 0, len(self.samples[ue])
        rows = self.samples[ue]
        while lo < hi:
            mid = (lo + hi) // 2
            if rows[mid].t <= t:
                found, lo = rows[mid], mid + 1
            else:
                hi = mid
        return found

    @classmethod
    def parse(cls, text: str, source: str = "trace") -> RadioTrace:
        """Parse `time_s,ue,rsrp_dbm,sinr_db,mcs[,cell]` rows after that header line.

        Blank lines and `#` comments are skipped. Raises `RadioTraceError` naming up to
        `MAX_TRACE_PROBLEMS` wrong fields as `source:line: field: what`.
        """
        problems: list[str] = []
        rows: dict[str, list[TraceSample]] = {}
        columns: tuple[str, ...] | None = None
        for number, line in _numbered(text.splitlines()):
            cells = [c.strip() for c in line.split(",")]
            where = f"{source}:{number}"
            if columns is None:
                header = tuple(cells)
                if header not in (TRACE_COLUMNS, (*TRACE_COLUMNS, "cell")):
                    expected = ",".join(TRACE_COLUMNS)
                    problems.append(
                        f"{where}: header: expected {expected!r} (optionally ',cell'), "
                        f"got {line[:60]!r}"
                    )
                    break
                columns = header
                continue
            if len(cells) != len(columns):
                problems.append(
                    f"{where}: expected {len(columns)} columns ({','.join(columns)}), "
                    f"got {len(cells)}"
                )
                continue
            row = dict(zip(columns, cells, strict=True))
            sample = _trace_row(row, where, problems)
            if sample is None:
                continue
            ue = row["ue"]
            previous = rows.get(ue)
            if previous and sample.t <= previous[-1].t:
                problems.append(
                    f"{where}: time_s: {sample.t:g} is not after UE {ue}'s previous sample "
                    f"({previous[-1].t:g})"
                )
                continue
            rows.setdefault(ue, []).append(sample)
        if columns is None and not problems:
            problems.append(f"{source}:1: header: the trace is empty")
        elif not problems and not rows:
            problems.append(f"{source}: no samples after the header")
        if problems:
            if len(problems) > MAX_TRACE_PROBLEMS:
                extra = len(problems) - MAX_TRACE_PROBLEMS
                problems = [*problems[:MAX_TRACE_PROBLEMS], f"{source}: {extra} more problem(s)"]
            raise RadioTraceError(problems)
        return cls({ue: tuple(s) for ue, s in rows.items()}, source)

    @classmethod
    def load(cls, path: str | Path) -> RadioTrace:
        """Read and parse a trace file (see `parse`); an unreadable file is a `ChannelError`."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ChannelError(f"{path}: cannot read the radio trace ({exc})") from None
        return cls.parse(text, str(path))


def _numbered(lines: Iterable[str]) -> Iterable[tuple[int, str]]:
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            yield number, line


def _number(row: dict[str, str], field: str, where: str, problems: list[str]) -> float | None:
    text = row[field]
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        problems.append(f"{where}: {field}: expected a number, got {text!r}")
        return None
    return value


def _trace_row(row: dict[str, str], where: str, problems: list[str]) -> TraceSample | None:
    """One data row as a sample, or None with its problems appended."""
    before = len(problems)
    t = _number(row, "time_s", where, problems)
    if t is not None and t < 0:
        problems.append(f"{where}: time_s: {t:g} is negative")
    if not row["ue"]:
        problems.append(f"{where}: ue: empty (a UE name is needed)")
    rsrp = _number(row, "rsrp_dbm", where, problems)
    low, high = RSRP_RANGE_DBM
    if rsrp is not None and not low <= rsrp <= high:
        problems.append(
            f"{where}: rsrp_dbm: {rsrp:g} is outside the {low:g}..{high:g} dBm a UE reports "
            f"(TS 38.133 §10.1)"
        )
    sinr = _number(row, "sinr_db", where, problems)
    low, high = SINR_RANGE_DB
    if sinr is not None and not low <= sinr <= high:
        problems.append(
            f"{where}: sinr_db: {sinr:g} is outside the {low:g}..{high:g} dB a UE reports "
            f"(TS 38.133 §10.1)"
        )
    mcs_text = row["mcs"]
    mcs = int(mcs_text) if mcs_text.lstrip("+-").isdigit() else None
    if mcs is None or not 0 <= mcs < len(MCS_TABLE_1):
        problems.append(
            f"{where}: mcs: expected a whole number 0..{len(MCS_TABLE_1) - 1} "
            f"(TS 38.214 Table 5.1.3.1-1), got {mcs_text!r}"
        )
    if len(problems) > before or t is None or rsrp is None or sinr is None or mcs is None:
        return None
    return TraceSample(t, rsrp, sinr, mcs, row.get("cell") or None)
