"""What a ground filter could reach on the rural_slope family if it knew the ground.

For each scene the true labels pick the ground returns; a surface is built from
those returns alone and every return is labelled ground when it stands at most
``t`` above that surface (and less than ``LOW`` below it: low outliers go). The
ground returns themselves are held out of the surface that judges them (the TIN
in ``FOLDS`` folds, the quadratic leaving each point out), so their heights are
what a filter's own surface would show them at. Swept over ``t``, this prints per
scene the least Type II reachable with Type I within each cap, the threshold
that reaches it, and over the scenes the worst / p90 / median, gentle and steep
apart (odd seeds steep), and the best single ``t`` for all scenes. Surfaces: ``tin`` (linear on the Delaunay triangulation), ``quad``
(the close fit's quadratic of the 12 nearest ground returns, refitted without
those high above it), ``true`` (the generator's own ground: the label noise
alone)::

    python benchmarks/ground_bound.py --seeds 1000-1011,1020-1031
    python benchmarks/ground_bound.py --seeds 1000-1011 --no-relief --surfaces quad
    python benchmarks/ground_bound.py --tails --isprs
    python benchmarks/ground_bound.py --echoes --seeds 1000-1031
    python benchmarks/ground_bound.py --lift --isprs --seeds 1000-1031

``--tails`` asks instead whether the ground's bend can be read from its lower tail:
scrub only adds returns above the ground, so the 3rd percentile of the ground's
height over the quadratic (``LOW_Q``) measures the surface's misfit without them. It
prints that figure per scene and, in its units, the ground's 97th / 99th percentiles
and the 10th / 25th / 50th of the non-ground returns up to 1 m: a threshold at a
multiple of it would part them where the scrub's quantiles stand above the ground's
in every scene, the ISPRS samples (``--isprs``) included.

``--echoes`` asks whether echo structure could mark the low returns instead: per
scene, the returns in height bands over the ground (``BANDS``) and the share of
them that are single returns and that are not the last of their pulse (something
lay behind them), for the family (heights over its true ground), for
Topography.laz (the one real survey at hand with return numbers; heights over the
12-point quadratic of its provider ground, so its class 1 below that ground's
noise is mostly ground the provider did not keep) and which echo fields the ISPRS
samples carry at all.

``--lift`` runs ``ground.nist`` (the stage alone, default parameters) and asks what
its own surface shows: per scene, the vegetation it took for ground (FP) at its
median height in units of the lower tail, once over the true ground's quadratic
(``L``) and once over the quadratic of what the stage took for ground (``Ls``,
each point left out), and what a cut at ``c`` x ``Ls`` on that surface (``CUTS``)
would make of Type I, Type II and kappa; the ISPRS samples (``--isprs``) beside.

A filter's own surface is fitted on what it takes for ground, not on the true
ground, so these are the best a rule on the height over a surface could do; a
filter that judges a return by more than its height is not bound by them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import Delaunay, cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from terrasift.synthetic.rural import rural_slope  # noqa: E402
from terrasift.workers.ground.closefit import _quad_heights  # noqa: E402

FOLDS = 20  # ground returns held out per TIN: 5 % at a time, so the rest keep their spacing
LOW = 1.0  # m: returns this far under the surface are outliers (the family's sit 1-6 m under)
K = 12  # the close fit's neighbours (``ground.nist``'s ``rough_fit``)
FLOOR = 0.15  # the close fit's floor (its refit's least scale is a quarter of it)
T = np.round(np.arange(0.0, 1.0001, 0.005), 3)
LOW_Q = 3.0  # percentile of the ground's heights taken as its lower tail
#: multiple of the lower tail: the least cut the ISPRS samples stand (5.9 samp61, 6.9
#: samp12, on the stage's own surface); ``--tails`` prints the ground's share above it
FAR = 6.0
TOP = 1.0  # m: non-ground up to this height over the surface (the close fit's ceiling)
#: m over the ground: the family's grass line (0.25), its least dead zone (0.6 is drawn
#: from 0.6-3.5; 0.5 the band edge below it), the close fit's ceiling (1), and 2 m.
BANDS = (0.25, 0.5, 1.0, 2.0)
CUTS = (1.0, 1.5, 2.0, 3.0)  # multiples of the stage surface's lower tail tried by ``--lift``


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def tin_heights(xy: np.ndarray, z: np.ndarray, ground: np.ndarray, seed: int) -> np.ndarray:
    """Height of every point over the TIN of the ground returns (ground held out by fold)."""
    g = np.flatnonzero(ground)
    fold = np.random.default_rng(seed).integers(0, FOLDS, g.size)
    out = np.empty(z.size)
    for f in range(-1, FOLDS):
        fit, at = (g, np.flatnonzero(~ground)) if f < 0 else (g[fold != f], g[fold == f])
        v = LinearNDInterpolator(Delaunay(xy[fit]), z[fit])(xy[at])
        bad = np.isnan(v)  # outside the hull: the nearest ground return's height
        if bad.any():
            v[bad] = z[fit[cKDTree(xy[fit]).query(xy[at[bad]])[1]]]
        out[at] = z[at] - v
    return out


def quad_heights(xyz: np.ndarray, ground: np.ndarray) -> np.ndarray:
    """Height of every point over the quadratic of its 12 nearest ground returns (itself left out)."""
    g = np.flatnonzero(ground)
    pos = np.full(ground.size, -1)
    pos[g] = np.arange(g.size)
    idx = np.arange(ground.size)
    return _quad_heights(xyz, idx, g, cKDTree(xyz[g, :2]), pos, K, FLOOR)[0]


def curves(h: np.ndarray, ground: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Type I and Type II (%) of the rule ``-LOW <= h <= t`` for every ``t`` of ``T``."""
    under = (h[:, None] >= -LOW) & (h[:, None] <= T[None, :])
    t1 = 100 * (ground[:, None] & ~under).sum(0) / max(int(ground.sum()), 1)
    t2 = 100 * (~ground[:, None] & under).sum(0) / max(int((~ground).sum()), 1)
    return t1, t2


def best(t1: np.ndarray, t2: np.ndarray, cap: float) -> tuple[float, float]:
    """Least Type II with Type I within ``cap``, and its threshold (nan: none)."""
    ok = np.flatnonzero(t1 <= cap)
    if ok.size == 0:
        return float("nan"), float("nan")
    j = ok[np.argmin(t2[ok])]
    return float(t2[j]), float(T[j])


def spread(v: list[float]) -> str:
    a = np.asarray(v)
    return f"{np.nanmax(a):5.2f} / {np.nanpercentile(a, 90):5.2f} / {np.nanmedian(a):5.2f} ({int((a > 5).sum())} > 5 %)"


def tails(h: np.ndarray, ground: np.ndarray) -> tuple[float, np.ndarray]:
    """The ground's lower-tail figure (minus its ``LOW_Q`` percentile over the surface)
    and, in its units, the ground's 97th / 99th and the low non-ground's 10 / 25 / 50th;
    last, the share (%) of the ground standing more than ``FAR`` x the figure up."""
    low = -float(np.percentile(h[ground], LOW_Q))
    up = np.percentile(h[ground], [97, 99])
    obj = h[~ground & (h >= -LOW) & (h <= TOP)]
    q = np.percentile(obj, [10, 25, 50]) if obj.size else np.full(3, np.nan)
    far = 100 * float(np.mean(h[ground] > FAR * low))
    return low, np.concatenate([np.r_[up, q] / low, [far]])


def print_tails(seeds: list[int], relief: bool, isprs: bool) -> None:
    """``--tails``: the lower-tail figure per scene over the 12-point quadratic of true ground."""
    print(
        f"scene   pts/m²  low (m)   ground q97 q99 / low   non-ground ≤ {TOP:g} m q10 q25 q50 / low"
        f"   ground > {FAR:g} x low %"
    )
    scenes: list[tuple[str, np.ndarray, np.ndarray]] = []
    for seed in seeds:
        sc = rural_slope(seed, relief=relief)
        scenes.append((str(seed), sc.xyz - np.r_[sc.xyz[:, :2].min(0), 0.0], sc.is_ground))
    if isprs:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from ground_accuracy import _samples

        for name, xyz, cls in _samples():
            scenes.append((name, xyz - np.r_[xyz[:, :2].min(0), 0.0], cls == 2))
    for name, xyz, ground in scenes:
        low, r = tails(quad_heights(xyz, ground), ground)
        area = float(np.prod(np.ptp(xyz[:, :2], axis=0)))
        print(
            f"{name:7s} {len(ground) / area:6.2f}  {low:6.3f}    {r[0]:5.2f} {r[1]:5.2f}"
            f"              {r[2]:5.2f} {r[3]:5.2f} {r[4]:5.2f}         {r[5]:5.2f}",
            flush=True,
        )


def _echo_row(name: str, dens: float, h: np.ndarray, rn: np.ndarray, nr: np.ndarray) -> str:
    cells = []
    for lo, hi in zip(BANDS[:-1], BANDS[1:], strict=True):
        m = (h > lo) & (h <= hi)
        n = int(m.sum())
        one = 100 * float(np.mean(nr[m] == 1)) if n else float("nan")
        behind = 100 * float(np.mean(rn[m] < nr[m])) if n else float("nan")
        cells.append(f"{n:6d} {one:5.1f} {behind:5.1f}")
    return f"{name:10s} {dens:5.2f}  " + "   ".join(cells)


def print_echoes(seeds: list[int]) -> None:
    """``--echoes``: single and not-last shares of the returns in ``BANDS`` over the ground."""
    import laspy

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from ground_accuracy import DATA

    bands = "   ".join(
        f"{lo:g}-{hi:g} m: n  1-of-1% not-last%"
        for lo, hi in zip(BANDS[:-1], BANDS[1:], strict=True)
    )
    print(f"scene      pts/m²  {bands}")
    for seed in seeds:
        sc = rural_slope(seed)
        h = sc.xyz[:, 2] - sc.surface(sc.xyz[:, 0], sc.xyz[:, 1])
        area = float(np.prod(np.ptp(sc.xyz[:, :2], axis=0)))
        rn, nr = sc.return_number, sc.number_of_returns
        print(_echo_row(str(seed), len(h) / area, h, rn, nr), flush=True)
    topo = DATA / "lidr" / "Topography.laz"
    if topo.exists():
        las = laspy.read(str(topo))
        keep = np.asarray(las.classification) != 9  # water
        xyz = np.column_stack([las.x, las.y, las.z])[keep]
        xyz = xyz - np.r_[xyz[:, :2].min(0), 0.0]
        ground = np.asarray(las.classification)[keep] == 2
        h = quad_heights(xyz, ground)
        rn = np.asarray(las.return_number)[keep]
        nr = np.asarray(las.number_of_returns)[keep]
        area = float(np.prod(np.ptp(xyz[:, :2], axis=0)))
        print(_echo_row("Topography", len(h) / area, np.where(ground, -np.inf, h), rn, nr))
        pulses = float(np.sum(rn == nr)) / area
        print(
            f"  (Topography: {pulses:.2f} pulses/m²; its provider ground: 1-of-1 {100 * np.mean(nr[ground] == 1):.1f} %, not-last {100 * np.mean(rn[ground] < nr[ground]):.1f} %)"
        )
    for f in sorted((DATA / "isprs").glob("samp*.laz")):
        las = laspy.read(str(f))
        fields = [
            d
            for d in ("return_number", "number_of_returns", "intensity", "gps_time")
            if np.ptp(np.asarray(las[d])) > 0
        ]
        print(
            f"{f.stem}: fields that vary: {', '.join(fields) or 'none (one return per point, no intensity)'}"
        )


def _scores(ground: np.ndarray, taken: np.ndarray) -> tuple[float, float, float]:
    """Type I, Type II and kappa (%)."""
    n = ground.size
    t1 = 100 * float(np.sum(ground & ~taken)) / max(int(ground.sum()), 1)
    t2 = 100 * float(np.sum(~ground & taken)) / max(int((~ground).sum()), 1)
    agree = float(np.sum(ground == taken)) / n
    chance = (ground.sum() * taken.sum() + (~ground).sum() * (~taken).sum()) / n / n
    return t1, t2, 100 * (agree - chance) / (1 - chance)


def print_lift(seeds: list[int], isprs: bool) -> None:
    """``--lift``: the stage's false ground over the true and over its own surface."""
    from terrasift.workers import registry

    stage = registry.get_stage("ground.nist")
    params = stage.params.preset("default")
    scenes: list[tuple[str, np.ndarray, np.ndarray]] = []
    for seed in seeds:
        sc = rural_slope(seed)
        scenes.append((str(seed), sc.xyz, sc.is_ground))
    if isprs:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from ground_accuracy import _samples

        scenes += [(name, xyz, cls == 2) for name, xyz, cls in _samples()]
    cuts = "  ".join(f"c {c:g}: I/II/dkappa" for c in CUTS)
    print(f"scene   pts/m²   I %  II %  kappa  FP  h/L  h/Ls    {cuts}")
    rows = []
    for name, xyz0, ground in scenes:
        xyz = xyz0 - np.r_[xyz0[:, :2].min(0), 0.0]
        taken = np.asarray(stage.run(xyz0, params), dtype=bool)
        h = quad_heights(xyz, ground)
        hs = quad_heights(xyz, taken)
        low = -float(np.percentile(h[ground], LOW_Q))
        low_s = -float(np.percentile(hs[taken], LOW_Q))
        fp = ~ground & taken
        t1, t2, k = _scores(ground, taken)
        cut = [_scores(ground, taken & ~(hs > c * low_s)) for c in CUTS]
        rows.append((name, t1, t2, k, cut))
        area = float(np.prod(np.ptp(xyz[:, :2], axis=0)))
        med = (np.median(h[fp]) / low, np.median(hs[fp]) / low_s) if fp.any() else (np.nan,) * 2
        cells = "  ".join(f"{a:4.2f}/{b:5.2f}/{c - k:+6.2f}" for a, b, c in cut)
        print(
            f"{name:7s} {len(ground) / area:5.2f}  {t1:5.2f} {t2:5.2f} {k:6.2f} {int(fp.sum()):4d}"
            f" {med[0]:5.2f} {med[1]:5.2f}    {cells}",
            flush=True,
        )
    fam = [r for r in rows if not r[0].startswith("samp")]
    if fam:
        print(
            "family, stage as it is: "
            + f"Type II {spread([r[2] for r in fam])}, Type I worst {max(r[1] for r in fam):.2f}"
        )
        for j, c in enumerate(CUTS):
            print(
                f"  cut at {c:g} x Ls: Type II {spread([r[4][j][1] for r in fam])}, "
                f"Type I worst {max(r[4][j][0] for r in fam):.2f}"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1000-1011,1020-1031", help="e.g. 1000-1011,1020-1031")
    ap.add_argument(
        "--no-relief", action="store_true", help="the scenes without their micro-relief"
    )
    ap.add_argument("--surfaces", default="tin,quad", help="of tin, quad, true")
    ap.add_argument("--caps", default="3,1", help="Type I caps (%%)")
    ap.add_argument("--tails", action="store_true", help="the lower-tail figure per scene")
    ap.add_argument(
        "--isprs", action="store_true", help="with --tails or --lift: the five ISPRS samples too"
    )
    ap.add_argument("--echoes", action="store_true", help="echo structure of the low returns")
    ap.add_argument("--lift", action="store_true", help="the stage's own surface (ground.nist)")
    args = ap.parse_args()
    if args.lift:
        print_lift(_seeds(args.seeds), args.isprs)
        return
    if args.echoes:
        print_echoes(_seeds(args.seeds))
        return
    if args.tails:
        print_tails(_seeds(args.seeds), not args.no_relief, args.isprs)
        return
    surfaces = args.surfaces.split(",")
    caps = [float(c) for c in args.caps.split(",")]
    rows = []
    print(
        "seed  pts/m² (box)  non-ground  "
        + "  ".join(f"{s} II@I≤{c:g} (t)" for s in surfaces for c in caps)
    )
    for seed in _seeds(args.seeds):
        sc = rural_slope(seed, relief=not args.no_relief)
        xyz = sc.xyz - np.r_[sc.xyz[:, :2].min(0), 0.0]
        ground = sc.is_ground
        h = {}
        for s in surfaces:
            if s == "tin":
                h[s] = tin_heights(xyz[:, :2], xyz[:, 2], ground, seed)
            elif s == "quad":
                h[s] = quad_heights(xyz, ground)
            else:
                h[s] = sc.xyz[:, 2] - sc.surface(sc.xyz[:, 0], sc.xyz[:, 1])
        row = {s: curves(h[s], ground) for s in surfaces}
        rows.append((seed, row))
        area = float(np.prod(np.ptp(xyz[:, :2], axis=0)))
        cells = "  ".join(
            "{:6.2f} ({:.3f})".format(*best(*row[s], c)) for s in surfaces for c in caps
        )
        print(f"{seed}  {len(ground) / area:11.2f}  {int((~ground).sum()):6d}  {cells}", flush=True)
    groups = [
        ("all", lambda s: True),
        ("gentle", lambda s: s % 2 == 0),
        ("steep", lambda s: s % 2 == 1),
    ]
    print("\nType II worst / p90 / median, each scene at its own best t:")
    for name, sel in groups:
        for s in surfaces:
            for c in caps:
                v = [best(*r[s], c)[0] for seed, r in rows if sel(seed)]
                if not v:
                    continue
                print(f"  {name:6s} {s:4s} Type I ≤ {c:g} %: {spread(v)}")
    print("One t for every scene (least worst Type II with worst Type I within the cap):")
    for s in surfaces:
        t1 = np.array([r[s][0] for _, r in rows])
        t2 = np.array([r[s][1] for _, r in rows])
        for c in caps:
            ok = np.flatnonzero(t1.max(0) <= c)
            if ok.size == 0:
                print(f"  {s:4s} Type I ≤ {c:g} %: none")
                continue
            j = ok[np.argmin(t2.max(0)[ok])]
            print(
                f"  {s:4s} Type I ≤ {c:g} %: t {T[j]:.3f} m, Type II {spread(list(t2[:, j]))}, "
                f"Type I worst {t1[:, j].max():.2f}"
            )


if __name__ == "__main__":
    main()
