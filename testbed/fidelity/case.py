"""A fidelity case: one published measurement of a real 5G system, as a file says it.

A case file (`scenarios/fidelity/*.yaml`) gives the system's radio as the source configured it
(a named profile and the fields it changes, in a scenario's `radio` keys), the source's probe
(packet size, interval, directions, round trip or not), what the source published (figures per
direction, components such as the HARQ share, a per-packet or histogram file) and where it
comes from (citation, repository, licence). A case may have variants, each changing only the
radio fields the source changed, with its own published figures.

    case = load_case(Path("scenarios/fidelity/srsran_urllc.yaml"))
    for variant in case.variants: variant.radio, variant.published["uplink"]["mean"]

Every error names the file and the key (`FidelityError`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from netem.directions import DIRECTIONS
from netem.nr.phy import NrError
from netem.nr.radio import RADIO_PROFILES, Radio
from testbed.errors import BadInput
from testbed.scenario.radios import ATTRS, changed
from testbed.units import UnitError, parse_duration

#: Where the library lives, beside the scenarios.
LIBRARY = Path(__file__).resolve().parents[2] / "scenarios" / "fidelity"
#: What a published figure may be, per direction or for the round trip (ms).
FIGURES = ("min", "p50", "mean", "p90", "p95", "p99")
#: What is measured: each direction one way, and the round trip of an echo.
MEASURES = (*DIRECTIONS, "rtt")
#: Components a source may publish (shares as fractions, steps in ms).
COMPONENTS = ("harq_share", "harq_step_ms", "segmented_share")


class FidelityError(BadInput):
    """A case file is wrong (the message names the file and the key), or names no case."""


@dataclass(frozen=True)
class Probe:
    """The source's probe: `size` bytes of UDP payload every `interval_s`, in `measures`."""

    size: int
    interval_s: float
    measures: tuple[str, ...]
    count: int
    #: When, after a TDD period's start, the source's probes were sent (s, drawn uniformly
    #: in this range; the interval is a multiple of the period, so each probe meets the grid
    #: there); None: anywhere in the period (a UE clock that drifts against the gNB's).
    phase_s: tuple[float, float] | None = None


@dataclass(frozen=True)
class Data:
    """A file of the source's own samples for one measure: per packet (a column of ms) or a
    histogram (DETERMINISTIC6G's CSV of bin and count), with the sentence that says where
    it is from."""

    path: Path
    kind: str  # "per_packet" | "histogram"
    column: str = "delay_ms"


@dataclass(frozen=True)
class Variant:
    """One configuration of the case's system and what was measured on it."""

    name: str
    radio: Radio
    changes: dict[str, Any]
    published: dict[str, dict[str, float]]
    floors: dict[str, float] = field(default_factory=dict)
    components: dict[str, Any] = field(default_factory=dict)
    data: dict[str, Data] = field(default_factory=dict)


@dataclass(frozen=True)
class Case:
    """A published measurement: its source, its probe and its variants."""

    name: str
    title: str
    path: Path
    source: dict[str, str]
    profile: str
    probe: Probe
    variants: tuple[Variant, ...]
    calibrated: str = ""
    #: What the model cannot produce that the source shows (printed with the verdict).
    not_modelled: str = ""
    #: The wired path beyond the radio, each way (a cloud server's distance), ms.
    wired_ms: float = 0.0


def _need(data: dict[str, Any], key: str, where: str, kind: type | tuple[type, ...]) -> Any:
    if key not in data:
        raise FidelityError(f"{where}: `{key}` is missing")
    value = data[key]
    if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
        raise FidelityError(f"{where}: `{key}` must be {_kind_name(kind)}, got {value!r}")
    return value


def _kind_name(kind: type | tuple[type, ...]) -> str:
    names = {str: "a string", int: "an integer", float: "a number", dict: "a mapping",
             list: "a list"}  # fmt: skip
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(names.get(k, k.__name__) for k in kinds)


def _unknown(data: dict[str, Any], allowed: tuple[str, ...], where: str) -> None:
    extra = sorted(set(data) - set(allowed))
    if extra:
        raise FidelityError(
            f"{where}: unknown key(s) {', '.join(extra)} (expected {', '.join(allowed)})"
        )


def _duration(value: Any, where: str) -> float:
    try:
        return parse_duration(value)
    except (UnitError, TypeError) as err:
        raise FidelityError(f"{where}: {err}") from None


def _figures(data: Any, where: str) -> dict[str, dict[str, float]]:
    if not isinstance(data, dict):
        raise FidelityError(f"{where}: must be a mapping of {', '.join(MEASURES)}")
    _unknown(data, MEASURES, where)
    out: dict[str, dict[str, float]] = {}
    for measure, figures in data.items():
        here = f"{where}.{measure}"
        if not isinstance(figures, dict) or not figures:
            raise FidelityError(f"{here}: must map some of {', '.join(FIGURES)} to ms")
        _unknown(figures, FIGURES, here)
        for name, value in figures.items():
            if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
                raise FidelityError(f"{here}.{name}: must be a positive number of ms")
        out[measure] = {k: float(v) for k, v in figures.items()}
    return out


def _radio(values: Any, base: Radio, where: str) -> tuple[Radio, dict[str, Any]]:
    if not isinstance(values, dict):
        raise FidelityError(f"{where}: must be a mapping of radio keys")
    allowed = ("profile", *ATTRS, "special_dl", "special_ul")
    _unknown(values, allowed, where)
    values = dict(values)
    for key in ("rlc_status", "core_delay", "ue_delay_ul", "ue_delay_dl"):
        if key in values:
            values[key] = _duration(values[key], f"{where}.{key}")
    try:
        radio = changed(values, base)
        radio.check()
    except (NrError, TypeError) as err:
        raise FidelityError(f"{where}: {err}") from None
    return radio, values


def _data(values: Any, folder: Path, where: str) -> dict[str, Data]:
    if not isinstance(values, dict):
        raise FidelityError(f"{where}: must map a measure to a file")
    _unknown(values, MEASURES, where)
    out = {}
    for measure, spec in values.items():
        here = f"{where}.{measure}"
        if (
            not isinstance(spec, dict)
            or len(spec) != 1
            or next(iter(spec))
            not in (
                "per_packet",
                "histogram",
            )
        ):
            raise FidelityError(f"{here}: must be {{per_packet: FILE}} or {{histogram: FILE}}")
        kind, name = next(iter(spec.items()))
        path = folder / str(name)
        if not path.is_file():
            raise FidelityError(f"{here}.{kind}: no file {path}")
        out[measure] = Data(path, kind)
    return out


def _variant(raw: Any, base: Radio, folder: Path, where: str) -> Variant:
    if not isinstance(raw, dict):
        raise FidelityError(f"{where}: must be a mapping")
    keys = ("name", "radio", "published", "floors", "components", "data")
    _unknown(raw, keys, where)
    name = _need(raw, "name", where, str)
    radio, changes = _radio(raw.get("radio", {}), base, f"{where}.radio")
    published = _figures(_need(raw, "published", where, dict), f"{where}.published")
    floors = raw.get("floors", {})
    if not isinstance(floors, dict) or any(
        k not in MEASURES or not isinstance(v, int | float) for k, v in floors.items()
    ):
        raise FidelityError(f"{where}.floors: must map {', '.join(MEASURES)} to ms")
    components = raw.get("components", {})
    if not isinstance(components, dict):
        raise FidelityError(f"{where}.components: must be a mapping")
    _unknown(components, COMPONENTS, f"{where}.components")
    data = _data(raw.get("data", {}), folder, f"{where}.data")
    return Variant(name, radio, changes, published, dict(floors), dict(components), data)


def load_case(path: Path) -> Case:
    """Read and check one case file."""
    where = str(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as err:
        raise FidelityError(f"{where}: cannot read it ({err.strerror})") from None
    except yaml.YAMLError as err:
        raise FidelityError(f"{where}: not YAML: {err}") from None
    if not isinstance(raw, dict):
        raise FidelityError(f"{where}: must be a mapping with case, source, radio, probe")
    keys = ("case", "title", "source", "radio", "probe", "variants", "calibrated",
            "not_modelled", "wired")  # fmt: skip
    _unknown(raw, keys, where)
    name = _need(raw, "case", where, str)
    source = _need(raw, "source", where, dict)
    for key in ("cite", "url", "licence"):
        _need(source, key, f"{where}: source", str)
    radio_raw = _need(raw, "radio", where, (str, dict))
    if isinstance(radio_raw, str):
        radio_raw = {"profile": radio_raw}
    profile = radio_raw.get("profile", "")
    if profile not in RADIO_PROFILES:
        raise FidelityError(
            f"{where}: radio.profile must name a radio of {', '.join(RADIO_PROFILES)}, "
            f"got {profile!r}"
        )
    base, _ = _radio(radio_raw, RADIO_PROFILES[profile], f"{where}: radio")
    probe_raw = _need(raw, "probe", where, dict)
    _unknown(probe_raw, ("size", "interval", "measures", "count", "phase"), f"{where}: probe")
    size = _need(probe_raw, "size", f"{where}: probe", int)
    if not 28 <= size <= 1400:
        raise FidelityError(f"{where}: probe.size must be 28..1400 bytes, got {size}")
    interval = _duration(_need(probe_raw, "interval", f"{where}: probe", (str, int, float)),
                         f"{where}: probe.interval")  # fmt: skip
    if not 0.001 <= interval <= 1.0:
        raise FidelityError(f"{where}: probe.interval must be 1 ms to 1 s")
    measures = tuple(_need(probe_raw, "measures", f"{where}: probe", list))
    if not measures or set(measures) - set(MEASURES):
        raise FidelityError(
            f"{where}: probe.measures must list some of {', '.join(MEASURES)}, got {measures}"
        )
    count = int(probe_raw.get("count", 1000))
    phase = None
    if "phase" in probe_raw:
        raw_phase = probe_raw["phase"]
        if not isinstance(raw_phase, list) or len(raw_phase) != 2:
            raise FidelityError(f"{where}: probe.phase must be [FROM, TO] in the TDD period")
        lo, hi = (_duration(x, f"{where}: probe.phase") for x in raw_phase)
        if not 0 <= lo <= hi <= interval:
            raise FidelityError(
                f"{where}: probe.phase must be FROM <= TO within the interval, 0 to "
                f"{interval * 1000:g} ms after a TDD period's start"
            )
        phase = (lo, hi)
    folder = path.parent
    variants_raw = _need(raw, "variants", where, list)
    if not variants_raw:
        raise FidelityError(f"{where}: variants must list at least one")
    variants = tuple(
        _variant(v, base, folder, f"{where}: variants[{i}]") for i, v in enumerate(variants_raw)
    )
    wired = _duration(raw.get("wired", 0), f"{where}: wired") * 1000
    return Case(
        name=name,
        title=str(raw.get("title", name)),
        path=path,
        source={k: str(v) for k, v in source.items()},
        profile=profile,
        probe=Probe(size, interval, measures, count, phase),
        variants=variants,
        calibrated=str(raw.get("calibrated", "")),
        not_modelled=str(raw.get("not_modelled", "")),
        wired_ms=wired,
    )


def library() -> list[Case]:
    """Every case of the library, by file name."""
    return [load_case(p) for p in sorted(LIBRARY.glob("*.yaml"))]


def find(names: list[str]) -> list[Case]:
    """The library's cases named (by `case:` or file stem); all of them for none."""
    cases = library()
    if not names:
        return cases
    by_name = {c.name: c for c in cases} | {c.path.stem: c for c in cases}
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise FidelityError(
            f"no fidelity case {', '.join(unknown)}; the library has "
            f"{', '.join(c.name for c in cases)}"
        )
    return [by_name[n] for n in names]


def shortened(case: Case, count: int) -> Case:
    """The same case with `count` probes per variant (the test suite's)."""
    return dataclasses.replace(case, probe=dataclasses.replace(case.probe, count=count))
