"""Figures: policy maps (MODEL §5 item 2), the box plot of the main comparison and the
paired differences of ``fleet-compare``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402

from .runinfo import atomic_write  # noqa: E402

Policy = Any  # an agents.base.Policy (duck-typed: utils sits below the agents)

TC_TABULAR = (0.0, 0.5)  # free / busy: the tabular state only sees TC > 0
_CMAP = ListedColormap(["#d9e6f2", "#d95f02"])  # pass, charge


# a partial_site policy's map is drawn at the default site: N_V / N_N, p_c, T_C / (T_C + N_N)
DEFAULT_SITE_FEATURES = (3 / 15, 0.8, 30 / 45)


MAP_ENCODINGS = ("partial", "partial_site")  # the states a map over its three axes can draw


@torch.no_grad()
def policy_map(policy: Policy, tcs: tuple[float, ...], n: int = 101,
               site_features: tuple[float, ...] = DEFAULT_SITE_FEATURES) -> torch.Tensor:
    """Actions on a grid of ``partial`` states: ``[len(tcs), n (soc_D), n (lowest soc)]``
    (a ``partial_site`` policy's with ``site_features`` appended: the default site's)."""
    if policy.encoding not in MAP_ENCODINGS:
        raise ValueError(f"policy maps need the partial encoding, {policy.name} uses "
                         f"{policy.encoding}")
    extra = site_features if policy.encoding == "partial_site" else ()
    soc = torch.linspace(0.0, 1.0, n)
    y, x = torch.meshgrid(soc, soc, indexing="ij")
    maps = []
    for tc in tcs:
        cols = [y, x, torch.full_like(x, tc), *(torch.full_like(x, f) for f in extra)]
        obs = torch.stack(cols, dim=-1).reshape(-1, len(cols))
        dev = next(iter(policy.buffers()), next(iter(policy.parameters()), torch.empty(0))).device
        maps.append(policy(obs.to(dev)).reshape(n, n).cpu())
    return torch.stack(maps)


def plot_policy_map(policy: Policy, tcs: tuple[float, ...] | None = None,
                    title: str | None = None):
    """Figure with one panel per ``TC`` value (default: the policy's ``map_tc_values``):
    orange = charge, pale = pass."""
    tcs = tuple(tcs or policy.map_tc_values)
    maps = policy_map(policy, tcs)
    fig, axes = plt.subplots(1, len(tcs), figsize=(2.6 * len(tcs) + 0.6, 2.9), sharey=True,
                             squeeze=False)
    for ax, tc, m in zip(axes[0], tcs, maps, strict=True):
        ax.imshow(m.numpy(), origin="lower", extent=(0, 100, 0, 100), cmap=_CMAP, vmin=0,
                  vmax=1, aspect="auto", interpolation="nearest")
        label = "free" if tc == 0 else ("busy" if tcs == TC_TABULAR else f"{tc:.1f}")
        ax.set_title(f"TC = {label}", fontsize=9)
        ax.set_xlabel("lowest soc of the others")
    axes[0][0].set_ylabel("soc at D")
    fig.suptitle(title or f"{policy.name}: charge (orange) / pass", fontsize=10)
    fig.tight_layout()
    return fig


def plot_decision_shares(shares: list[tuple[torch.Tensor, str, tuple[float, float]]],
                         title: str):
    """Panels of the share of *charge* among a state-based policy's decisions per cell
    (``[ny, nx]``, NaN where it met no state), each with its x label and x range; y is
    ``soc_D`` in [0, 100]. Pale = always pass, orange = always charge, blank = not visited."""
    from matplotlib.colors import LinearSegmentedColormap

    cmap = LinearSegmentedColormap.from_list("share", ["#d9e6f2", "#d95f02"])
    cmap.set_bad("white")
    fig, axes = plt.subplots(1, len(shares), figsize=(3.4 * len(shares) + 0.8, 3.1),
                             sharey=True, squeeze=False)
    im = None
    for ax, (m, xlabel, (x0, x1)) in zip(axes[0], shares, strict=True):
        im = ax.imshow(m.numpy(), origin="lower", extent=(x0, x1, 0, 100), cmap=cmap, vmin=0,
                       vmax=1, aspect="auto", interpolation="nearest")
        ax.set_xlabel(xlabel)
    axes[0][0].set_ylabel("soc at D")
    if im is not None:
        fig.colorbar(im, ax=axes[0].tolist(), shrink=0.85, label="share of charge decisions")
    fig.suptitle(title, fontsize=10)
    return fig


def save_figure(fig, path: str | Path) -> Path:
    path = Path(path)
    out = atomic_write(path, lambda f: fig.savefig(f, format=path.suffix.lstrip(".") or "png",
                                                   dpi=110), mode="wb")
    plt.close(fig)
    return out


def whisker_span(values: list[float]) -> tuple[float, float]:
    """The ends of a box plot's whiskers over ``values`` (Tukey's, as matplotlib draws them:
    the most extreme values within 1.5 interquartile ranges of the quartiles)."""
    x = torch.tensor(values, dtype=torch.float64)
    q1, q3 = (float(q) for q in torch.quantile(x, torch.tensor([0.25, 0.75],
                                                               dtype=torch.float64)))
    iqr = q3 - q1
    inside = x[(x >= q1 - 1.5 * iqr) & (x <= q3 + 1.5 * iqr)]
    return float(inside.min()), float(inside.max())


def _median(values: list[float] | torch.Tensor) -> float:
    """The median (the mean of the two middle values of an even count)."""
    return float(torch.quantile(torch.as_tensor(values, dtype=torch.float64), 0.5))


def robust_limits(rows: dict[str, list[float]] | list[list[float]], keep: float = 0.0,
                  reach: float = 3.0) -> tuple[float, float]:
    """Axis limits for box plots of several rows that one outlier row cannot squash.

    Each row spans its whiskers (:func:`whisker_span`: a row's own outliers, a failed
    simulation tens of % below, lie beyond them). The typical row spans from the median of
    the rows' lower whisker ends to the median of their upper ends; the band around it
    reaches ``reach`` times the larger of that span and the median row's width further on
    each side. A row whose median lies outside the band (a policy that fails in most
    simulations) is left out of the limits, and the others' whiskers count as far as the
    band: what lies beyond the axis is marked on its edge and counted by the plot instead of
    flattening every other box. ``keep`` (the baseline's 0) stays in view when it lies in
    the band. A margin of 5 % of the range (at least 0.5) is added on each side."""
    values = [list(r) for r in (rows.values() if isinstance(rows, dict) else rows) if len(r)]
    if not values:
        return -1.0, 1.0
    spans = [whisker_span(r) for r in values]
    lows = torch.tensor([a for a, _ in spans], dtype=torch.float64)
    highs = torch.tensor([b for _, b in spans], dtype=torch.float64)
    medians = torch.tensor([_median(r) for r in values], dtype=torch.float64)
    core_lo, core_hi = _median(lows), _median(highs)
    width = _median(highs - lows)
    tol = reach * max(width, core_hi - core_lo) or 1.0
    band_lo, band_hi = core_lo - tol, core_hi + tol
    near = (medians >= band_lo) & (medians <= band_hi)
    if not bool(near.any()):  # no typical row (two rows far apart): show them all
        lo, hi = float(lows.min()), float(highs.max())
    else:
        lo = max(float(lows[near].min()), band_lo)
        hi = min(float(highs[near].max()), band_hi)
    if band_lo <= keep <= band_hi:
        lo, hi = min(lo, keep), max(hi, keep)
    pad = max(0.05 * (hi - lo), 0.5)
    return lo - pad, hi + pad


STRIP_POINTS = 300  # rows of at most this many points are drawn point by point too


def _robust_boxes(ax, rows: dict[str, list[float]], ylabel: str, points: bool = False) -> None:
    """Box plots of ``rows`` on :func:`robust_limits`; the points of a row beyond the axis
    are drawn as a triangle on its edge and counted in the row's label (with the row's
    median where that lies beyond it too). With ``points``, a row of at most
    :data:`STRIP_POINTS` values is also drawn point by point, jittered sideways."""
    data = [list(v) for v in rows.values()]
    ax.boxplot([d if d else [float("nan")] for d in data], showfliers=True,
               flierprops={"markersize": 2})
    if points:
        gen = torch.Generator().manual_seed(0)  # the same figure for the same data
        for i, vs in enumerate(data, start=1):
            if 0 < len(vs) <= STRIP_POINTS:
                x = i + 0.12 * (torch.rand(len(vs), generator=gen, dtype=torch.float64) - 0.5)
                ax.scatter(x.tolist(), vs, s=6, alpha=0.45, color="tab:blue", zorder=3)
    lo, hi = robust_limits(rows)
    ax.set_ylim(lo, hi)
    labels = []
    for i, (name, vs) in enumerate(zip(rows, data, strict=True), start=1):
        below, above = sum(v < lo for v in vs), sum(v > hi for v in vs)
        notes = []
        for n, edge, marker, where in ((below, lo, "v", "below"), (above, hi, "^", "above")):
            if n:
                ax.scatter([i], [edge], marker=marker, s=30, color="firebrick",
                           clip_on=False, zorder=5)
                notes.append(f"{n} {where}")
        if vs:
            med = _median(vs)
            if not lo <= med <= hi:
                notes.append(f"median {med:+.3g}")
        labels.append(name + ("\n" + ", ".join(notes) if notes else ""))
    ax.set_xticks(range(1, len(rows) + 1), labels, rotation=15, fontsize=8)
    if lo < 0.0 < hi:
        ax.axhline(0.0, color="grey", lw=0.8, ls="--")
    ax.set_ylabel(ylabel)


def plot_gain_boxplot(gains: dict[str, list[float]], title: str):
    """Box plot of each simulation's trips as % over the benchmark's mean, per policy, on an
    axis one outlier row cannot squash (:func:`robust_limits`; points beyond it marked on
    the edge and counted in the row's label)."""
    fig, ax = plt.subplots(figsize=(1.5 * len(gains) + 2, 3.8))
    _robust_boxes(ax, gains, "trips, % over rule mean")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_paired_differences(diffs: dict[str, list[float]], baseline: str, title: str):
    """Box plot, per result, of its paired differences in trips from ``baseline``: each
    simulation's (each site's) trips minus the baseline's on the same site, with the points
    themselves where there are few, on the same robust axis as :func:`plot_gain_boxplot`."""
    fig, ax = plt.subplots(figsize=(1.5 * len(diffs) + 2.4, 3.8))
    _robust_boxes(ax, diffs, f"trips minus {baseline}'s, per site", points=True)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_learning_curves(curves: dict[str, dict[int, list[tuple[float, ...]]]]):
    """Evaluation gain over the rule against training wall time: one colour per learned run,
    one line per training seed. Points are ``(seconds, gain %)`` or ``(seconds, gain %,
    failure rate)``.

    The axis fits the evaluations without failures, whatever their range (a run that stays
    at -10 % is drawn, not cut off); an evaluation with failures (tens of % below, early in
    a run) would flatten every other curve, so where it falls below that range it is drawn
    on the axis's lower edge as an ``x`` and counted in the legend."""
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    points = [pt for s in curves.values() for pts in s.values() for pt in pts]
    safe = [pt[1] for pt in points if len(pt) < 3 or pt[2] == 0]
    fit = safe or [pt[1] for pt in points] or [-1.0, 1.0]
    pad = 0.05 * (max(fit) - min(fit)) + 0.5
    lo, hi = min(min(fit) - pad, -0.5), max(max(fit) + pad, 0.5)  # the rule's 0 in view
    below = 0
    for i, (name, seeds) in enumerate(curves.items()):
        colour = colours[i % len(colours)]
        for j, (_, pts) in enumerate(sorted(seeds.items())):
            if not pts:
                continue
            t = [pt[0] / 60 for pt in pts]
            g = [max(pt[1], lo) for pt in pts]
            ax.plot(t, g, color=colour, lw=1.0, alpha=0.8, label=name if j == 0 else None)
            out = [(x, lo) for x, pt in zip(t, pts, strict=True) if pt[1] < lo]
            if out:
                below += len(out)
                ax.scatter(*zip(*out, strict=True), marker="x", s=14, color=colour,
                           clip_on=False, zorder=3)
    if below:
        ax.scatter([], [], marker="x", color="grey",
                   label=f"{below} evaluations with failures, below the axis")
    ax.set_ylim(lo, hi)
    ax.axhline(0.0, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("training wall time (min)")
    ax.set_ylabel("eval gain over rule (%)")
    ax.set_title("learning curves (training-evaluation set, one line per seed)", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


PARAM_LABELS = {"p_c": "closure probability p_c", "t_c": "charging ticks T_C",
                "n_vehicles": "vehicles N_V"}


def plot_sweep(rows: list[dict], param: str, title: str):
    """Gain in trips over the rule (± 95% CI) per policy against the swept parameter; a point
    whose policy failed in some simulation is circled in red, the best policy known at each
    point (the ``best_known`` row) is drawn as a black dashed line."""
    fig, ax = plt.subplots(figsize=(5.6, 3.6))
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    failed_label = "fails in some simulations"
    for name in policies:
        pts = sorted((r["value"], r["gain_pct"], r["gain_ci95"] or 0.0, r["failure_rate"])
                     for r in rows if r["policy"] == name and r["gain_pct"] is not None)
        if not pts:
            continue
        x, y, ci, fail = zip(*pts, strict=True)
        style = dict(color="black", ls="--", lw=1.4) if name == "best_known" else dict(lw=1.2)
        ax.errorbar(x, y, yerr=ci, marker="o", ms=3.5, capsize=2.5, label=name, **style)
        bad = [(xi, yi) for xi, yi, f in zip(x, y, fail, strict=True) if f > 0]
        if bad:
            ax.scatter(*zip(*bad, strict=True), s=70, facecolors="none", edgecolors="red",
                       lw=1.3, zorder=5, label=failed_label)
            failed_label = None
    ax.axhline(0.0, color="grey", lw=0.8, ls="--")
    ax.set_xlabel(PARAM_LABELS.get(param, param))
    ax.set_ylabel("trips gain over rule (%)")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return fig
