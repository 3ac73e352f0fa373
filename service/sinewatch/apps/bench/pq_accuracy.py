"""The power-quality section of ``sinewatch bench accuracy``: the scenario families of
:mod:`sinewatch.scenarios.power_quality_iec` (unbalance, harmonics, with exact truth) run
through the measurement code the daemon's power-quality stage uses, scored against the
accuracy limits of IEC 61000-4-7 class I and IEC 61000-4-30 class A, with pqopen-lib run
on the same waveforms beside it when the optional extra is installed.

Selected by ``sinewatch bench accuracy --scenarios pq`` (or ``tag:pq``, or names and
globs of the power-quality scenarios, ``pq-unbalance-*``); not part of the default run.

What runs, as in :class:`sinewatch.power_quality.stage.PqStage`:

* harmonics: one :class:`~sinewatch.power_quality.harmonics.HarmonicAnalyser` per channel
  (``HarmonicParams(nominal_frequency_hz, max_harmonic=50)``, what a harmonics rule builds),
  fed in blocks of :data:`BLOCK` samples; its harmonic subgroups (orders 2..50), THD
  (orders 2..40, as IEC 61000-4-7 defines it) and window frequency are scored on every window;
* unbalance: for three-phase scenarios, the group's analyser (three columns, phase a
  synchronising the windows, what a group with aggregation builds) and
  :func:`~sinewatch.power_quality.reports.window_sequence`: u2 and u0 of every window.

Limits (:data:`sinewatch.power_quality.limits.LIMITS`, as recalled: check the standards
before quoting compliance): harmonics, IEC 61000-4-7 class I, 5 % of the reading at or
above 1 % of nominal, 0.05 % of nominal below; THD, for which 61000-4-7 sets no accuracy,
judged like a harmonic reading; u2 and u0, IEC 61000-4-30 class A, 0.15 percentage points;
frequency, class A, 10 mHz. Nominal is the declared input, 1 per unit RMS (every
scenario's fundamental, or positive sequence, is 1). A row's ratio is the worst
``|error| / limit`` over its windows, phases and orders (<= 1: PASS); its error and limit
are those of that worst reading.

pqopen (:func:`sinewatch.power_quality.pqopen_reference.run_pqopen`) is scored the same
way on its 10/12-cycle windows, its first and last dropped (it starts at the first zero
crossing), on the orders it computes (up to 41 at 60 Hz and 10 kHz) and its THD over
2..40 against the truth over 2..40; it does not report the window frequency here.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from sinewatch import scenarios as sc_registry
from sinewatch.power_quality.harmonics import HarmonicAnalyser, HarmonicParams, HarmonicWindow
from sinewatch.power_quality.limits import LIMITS, class_i_limit
from sinewatch.power_quality.reports import window_sequence
from sinewatch.scenarios.power_quality_iec import PqScenario, PqTruth, get_pq, pq_names

PQ_TAG = "pq"  # --scenarios pq (or tag:pq): every power-quality scenario
BLOCK = 1000  # samples per block fed to the analysers (0.1 s at 10 kHz)
NOMINAL_RMS = 1.0  # the declared input, per unit
DOCS_BEGIN = "<!-- accuracy-pq-results:begin -->"
DOCS_END = "<!-- accuracy-pq-results:end -->"

# first match wins: the interharmonic unbalance family before plain unbalance
FAMILIES = (
    ("unbalance with a 5 % interharmonic", "pq-unbalance-*-interharmonic-*"),
    ("unbalance", "pq-unbalance-*hz-u2-*pct", "pq-unbalance-*hz-u2-*pct-[mp]5"),
    ("unbalance with harmonics", "pq-unbalance-*-harmonics*"),
    ("harmonics 2..50 at 1-10 %", "pq-harmonics-*-all*"),
    ("harmonics 2..50 at 0.1-0.9 %", "pq-harmonics-*-low*"),
    ("single harmonic (5th, 10 %)", "pq-harmonic-*-single"),
    ("interharmonics 1-5 % with harmonics", "pq-interharmonics-*"),
    ("single interharmonic (2.5 f, 5 %)", "pq-interharmonic-*-single"),
)


def family(name: str) -> str:
    for fam, *globs in FAMILIES:
        if any(fnmatch.fnmatchcase(name, g) for g in globs):
            return fam
    return "other"


def split_patterns(patterns: Iterable[str] | None) -> tuple[list[str] | None, list[str]]:
    """The ``--scenarios`` patterns for the single-channel bench (None: none given, the
    default run) and the power-quality scenario names they select: ``pq``/``tag:pq`` all
    of them, a name or glob those it matches (a glob may select from both)."""
    if patterns is None:
        return None, []
    pq_all = pq_names()
    regular: list[str] = []
    chosen: list[str] = []
    for p in patterns:
        if p in (PQ_TAG, f"tag:{PQ_TAG}"):
            hits = pq_all
        else:
            hits = fnmatch.filter(pq_all, p)
            if not hits or fnmatch.filter(sc_registry.names(), p):
                regular.append(p)  # a glob may match single-channel scenarios too
        chosen.extend(h for h in hits if h not in chosen)
    return regular, chosen


def _worst(err: np.ndarray, lim: np.ndarray) -> dict[str, float]:
    """Worst ``|err| / lim``, with the error and limit of that reading."""
    ratio = np.abs(err) / lim
    i = int(np.nanargmax(ratio)) if np.isfinite(ratio).any() else 0
    e, li = float(np.abs(err).flat[i]), float(lim.flat[i])
    r = float(ratio.flat[i])
    if not np.isfinite(ratio).all():  # a missing reading fails
        r = math.inf
    return {"error": e, "limit": li, "ratio": r}


def _thd(rms: np.ndarray, top: int) -> np.ndarray:
    thd: np.ndarray = np.sqrt(np.sum(rms[..., 2 : top + 1] ** 2, axis=-1)) / rms[..., 1]
    return thd


def _windows(analyser: HarmonicAnalyser, x: np.ndarray, fs: float) -> list[HarmonicWindow]:
    out: list[HarmonicWindow] = []
    for i in range(0, x.shape[0], BLOCK):
        out += analyser.update(x[i : i + BLOCK], round(i * 1e9 / fs))
    return out


def sinewatch_scores(sc: PqScenario, x: np.ndarray, truth: PqTruth) -> dict[str, dict[str, float]]:
    """The daemon's measurements of ``x`` ((n, P)) scored against ``truth``."""
    fs, nominal = sc.sample_rate_hz, sc.nominal_frequency_hz
    thd_true = _thd(truth.harmonic_rms, 40)
    g = truth.groups
    # quantity -> (the window's array, the truth per phase, orders scored)
    arrays = {
        "harmonics": ("harmonic_subgroup_rms", g["subgroup_rms"], slice(2, None)),
        "harmonic_groups": ("harmonic_group_rms", g["group_rms"], slice(2, None)),
        "interharmonic_groups": ("interharmonic_group_rms", g["ig_rms"], slice(1, None)),
        "interharmonic_subgroups": ("interharmonic_centred_subgroup_rms", g["isg_rms"], slice(1, None)),
    }
    ratios = {"thd": thd_true, "thdg": g["thdg"], "thds": g["thds"]}
    errs: dict[str, list[np.ndarray]] = {k: [] for k in (*arrays, *ratios, "frequency")}
    lims: dict[str, list[np.ndarray]] = {k: [] for k in errs}
    for p in range(sc.n_phases):  # one analyser per channel, as a harmonics rule builds
        an = HarmonicAnalyser(fs, HarmonicParams(nominal_frequency_hz=nominal, max_harmonic=50))
        for w in _windows(an, x[:, p], fs):
            for key, (attr, true, orders) in arrays.items():
                errs[key].append(getattr(w, attr)[0, orders] - true[p, orders])
                lims[key].append(class_i_limit(true[p, orders], NOMINAL_RMS))
            for key, true in ratios.items():
                errs[key].append(np.array([getattr(w, key)[0] - true[p]]))
                lims[key].append(class_i_limit(true[p : p + 1], 1.0))
            errs["frequency"].append(np.array([w.frequency_hz - truth.frequency_hz]))
            lims["frequency"].append(np.array([LIMITS["frequency_hz"]]))
    out = {k: _worst(np.concatenate(errs[k]), np.concatenate(lims[k])) for k in errs}
    if sc.n_phases == 3 and truth.u2 is not None and truth.u0 is not None:
        group = HarmonicAnalyser(fs, HarmonicParams(nominal_frequency_hz=nominal, n_channels=3, reference_channel=0))
        seq = [window_sequence(w) for w in _windows(group, x, fs)]
        lim = np.full(len(seq), LIMITS["u2_absolute"])
        out["u2"] = _worst(np.array([float(s.u2) - truth.u2 for s in seq]), lim)
        out["u0"] = _worst(np.array([float(s.u0) - truth.u0 for s in seq]), lim)
    return out


def pqopen_scores(sc: PqScenario, x: np.ndarray, truth: PqTruth) -> dict[str, dict[str, float]]:
    """pqopen-lib's 10/12-cycle values of ``x`` scored against ``truth`` (needs the extra)."""
    from sinewatch.power_quality.pqopen_reference import run_pqopen

    r = run_pqopen(x, sc.sample_rate_hz, sc.nominal_frequency_hz)
    steady = slice(1, -1)  # its first window starts at its first zero crossing
    h = r.harmonic_rms[steady]  # (W, P, top + 1)
    top = h.shape[2] - 1
    c = truth.harmonic_rms[:, : top + 1]
    lim = np.broadcast_to(class_i_limit(c[:, 2:], NOMINAL_RMS), h[:, :, 2:].shape)
    thd40 = _thd(truth.harmonic_rms, 40)
    thd = r.thd[steady]
    out = {
        "harmonics": _worst(h[:, :, 2:] - c[None, :, 2:], lim),
        "thd": _worst(thd - thd40[None], np.broadcast_to(class_i_limit(thd40, 1.0), thd.shape)),
        "max_order": {"error": math.nan, "limit": math.nan, "ratio": float(top)},
    }
    if r.u2 is not None and r.u0 is not None and truth.u2 is not None and truth.u0 is not None:
        u2, u0 = r.u2[steady], r.u0[steady]
        out["u2"] = _worst(u2 - truth.u2, np.full(u2.shape, LIMITS["u2_absolute"]))
        out["u0"] = _worst(u0 - truth.u0, np.full(u0.shape, LIMITS["u2_absolute"]))
    return out


def pqopen_available() -> bool:
    from sinewatch.power_quality.pqopen_reference import available

    return available()


def run_pq(names: Iterable[str], with_pqopen: bool | None = None) -> list[dict[str, Any]]:
    """One record per scenario: ``scenario``, ``family``, ``nominal_frequency_hz``,
    ``frequency_hz``, ``sinewatch`` and ``pqopen`` (quantity -> error, limit, ratio;
    ``pqopen`` is None when not installed, a string when it raised)."""
    if with_pqopen is None:
        with_pqopen = pqopen_available()
    records = []
    for name in names:
        sc = get_pq(name)
        truth = sc.pq_truth
        y, _ = sc.generate()
        x = y.reshape(y.shape[0], -1)
        ref: dict[str, Any] | str | None = None
        if with_pqopen:
            try:
                ref = pqopen_scores(sc, x, truth)
            except (ValueError, IndexError, KeyError, ArithmeticError) as exc:  # pqopen failing: a table cell
                ref = f"pqopen raised {type(exc).__name__}: {exc}"
        records.append(
            {
                "scenario": name,
                "family": family(name),
                "nominal_frequency_hz": sc.nominal_frequency_hz,
                "frequency_hz": sc.frequency_hz,
                "sinewatch": sinewatch_scores(sc, x, truth),
                "pqopen": ref,
            }
        )
    return records


QUANTITIES = (
    # key, label, limit text, unit scale, unit
    ("harmonics", "harmonic subgroups 2..50", "IEC 61000-4-7 class I", 100.0, " %"),
    ("harmonic_groups", "harmonic groups 2..50", "IEC 61000-4-7 class I", 100.0, " %"),
    ("interharmonic_groups", "interharmonic groups 1..50", "IEC 61000-4-7 class I", 100.0, " %"),
    ("interharmonic_subgroups", "interharmonic centred subgroups 1..50", "IEC 61000-4-7 class I", 100.0, " %"),
    ("thd", "THD", "like a class I reading", 100.0, " %"),
    ("thdg", "THDG", "like a class I reading", 100.0, " %"),
    ("thds", "THDS", "like a class I reading", 100.0, " %"),
    ("u2", "u2", "IEC 61000-4-30 class A", 100.0, " pt"),
    ("u0", "u0", "IEC 61000-4-30 class A", 100.0, " pt"),
    ("frequency", "frequency", "IEC 61000-4-30 class A", 1000.0, " mHz"),
)


def _num(x: float, unit: str) -> str:
    if not math.isfinite(x):
        return "inf" if x > 0 else "-"
    return f"{x:.2g}{unit}" if abs(x) < 0.01 else f"{x:.3g}{unit}"


def _verdict(ratio: float) -> str:
    return "PASS" if ratio <= 1.0 else "FAIL"


def _ratio_cell(s: dict[str, float] | None) -> str:
    return "-" if s is None else f"{s['ratio']:.3g} {_verdict(s['ratio'])}"


def render_markdown(records: list[dict[str, Any]], installed: bool) -> str:
    """The section: worst ratio per family and quantity, then every scenario's rows."""
    ref_note = (
        "pqopen-lib is not installed (`pip install '.[pqopen]'`): its column says so"
        if not installed
        else f"pqopen-lib {_pqopen_version()} run on the same samples"
    )
    lines = [
        "### Power quality: IEC 61000-4-7 class I and IEC 61000-4-30 class A",
        "",
        (
            "Harmonic subgroups of orders 2..50 and THD over 2..40 from the daemon's harmonic analyser "
            "(one per channel), u2 and u0 from its three-phase group analyser, window frequency; "
            "noise-free signals with exact truth, every 10/12-cycle window of 2 s at 10 kHz. "
            "Limits: harmonics 5 % of the reading at or above 1 % of nominal, 0.05 % of nominal below "
            "(class I); THD judged like a harmonic reading (the standard sets none); u2, u0 within "
            "0.15 percentage points and frequency within 10 mHz (class A); nominal 1 per unit. "
            f"Ratio: worst |error| / limit over windows, phases and orders (<= 1 PASS). {ref_note}; "
            "pqopen's THD is over 2..40 (scored against the truth over 2..40), its harmonics up to "
            "the order its FFT reaches (41 at 60 Hz), its first and last windows dropped."
        ),
        "",
        "#### Worst ratio per family",
        "",
        "| family | scenarios | quantity | sinewatch | pqopen |",
        "|---|---|---|---|---|",
    ]
    fams = list(dict.fromkeys(r["family"] for r in records))
    for fam in fams:
        recs = [r for r in records if r["family"] == fam]
        for key, label, *_ in QUANTITIES:
            sw = [r["sinewatch"][key] for r in recs if key in r["sinewatch"]]
            if not sw:
                continue
            worst_sw = max(sw, key=lambda s: s["ratio"])
            lines.append(
                f"| {fam} | {len(recs)} | {label} | {_ratio_cell(worst_sw)} | {_family_ref(recs, key, installed)} |"
            )
    lines += [
        "",
        "#### Every scenario",
        "",
        "| scenario | quantity | limit | sinewatch worst error | limit there | ratio | pqopen worst error | ratio |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        for key, label, std, scale, unit in QUANTITIES:
            s = r["sinewatch"].get(key)
            if s is None:
                continue
            ref = r["pqopen"]
            if isinstance(ref, dict) and key in ref:
                ref_err, ref_ratio = _num(scale * ref[key]["error"], unit), _ratio_cell(ref[key])
            elif isinstance(ref, str):
                ref_err, ref_ratio = "error", ref.replace("|", "/")
            else:
                ref_err, ref_ratio = ("not installed", "-") if not installed else ("not reported", "-")
            lines.append(
                f"| `{r['scenario']}` | {label} | {std} | {_num(scale * s['error'], unit)} | "
                f"{_num(scale * s['limit'], unit)} | {_ratio_cell(s)} | {ref_err} | {ref_ratio} |"
            )
    lines.append("")
    return "\n".join(lines)


def _family_ref(recs: list[dict[str, Any]], key: str, installed: bool) -> str:
    if not installed:
        return "not installed"
    refs = [r["pqopen"] for r in recs]
    if any(isinstance(x, str) for x in refs):
        return "error"
    vals = [x[key] for x in refs if isinstance(x, dict) and key in x]
    return _ratio_cell(max(vals, key=lambda s: s["ratio"])) if vals else "not reported"


def _pqopen_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pqopen-lib")
    except PackageNotFoundError:
        return "?"
