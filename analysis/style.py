"""Figure style for the paper's single column (3.5 in wide, fonts >= 7 pt) and stable colours.

Colours are assigned per algorithm NAME, deterministically: the paper's algorithms and the
baselines have fixed colours; any other name (a new algorithm registered by a plugin) takes
the next free colour of `_SPARE` in alphabetical order of the unknown names present, so the
same experiment always gives the same colours and no code change is needed for a new name.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

COLUMN_WIDTH_IN = 3.5
DOUBLE_WIDTH_IN = 7.16
FONT_PT = 8
SMALL_PT = 7  # never below 7 pt

KNOWN_COLOURS = {
    "mappo": "#d62728",
    "vdn": "#1f77b4",
    "qmix": "#2ca02c",
    "coma": "#ff7f0e",
    "ippo": "#9467bd",
    "optimal": "#000000",
    "greedy": "#7f7f7f",
    "adr": "#8c564b",
    "random": "#bcbd22",
    "fixed": "#17becf",
}
_SPARE = (
    "#e377c2",
    "#393b79",
    "#637939",
    "#8c6d31",
    "#843c39",
    "#7b4173",
    "#3182bd",
    "#e6550d",
    "#31a354",
    "#756bb1",
    "#636363",
    "#9c9ede",
)
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "h", "*", "p")
# Distinct dash patterns: with distinct markers, two series on the same points stay visible
# (issue 16: IPPO's line sat exactly under MAPPO's and appeared only in the legend).
LINE_STYLES = ("-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1)), (0, (1, 2)), (0, (8, 2)), (0, (3, 1, 1, 1)))


def _base(name: str) -> str:
    return name.split(" (")[0].strip().lower()


def colour_map(names) -> dict[str, str]:
    """name -> colour, deterministic for a given set of names (see the module docstring)."""
    names = sorted(set(names))
    out: dict[str, str] = {}
    used = set()
    for n in names:
        c = KNOWN_COLOURS.get(_base(n))
        if c is not None:
            out[n] = c
            used.add(c)
    spare = [c for c in _SPARE if c not in used]
    unknown = [n for n in names if n not in out]
    for i, n in enumerate(unknown):
        out[n] = spare[i % len(spare)]
    return out


def marker_map(names) -> dict[str, str]:
    return {n: MARKERS[i % len(MARKERS)] for i, n in enumerate(sorted(set(names)))}


def line_style_map(names) -> dict[str, object]:
    """name -> a dash pattern, distinct for up to len(LINE_STYLES) names (sorted order)."""
    return {n: LINE_STYLES[i % len(LINE_STYLES)] for i, n in enumerate(sorted(set(names)))}


def hollow(index: int) -> bool:
    """Every second series gets hollow markers, so a marker drawn on top of another shows both."""
    return index % 2 == 1


def context():
    """A matplotlib rc context with this style (the global rcParams stay untouched)."""
    return plt.rc_context(RC)


RC = {
    "font.size": FONT_PT,
    "axes.titlesize": FONT_PT,
    "axes.labelsize": FONT_PT,
    "xtick.labelsize": SMALL_PT,
    "ytick.labelsize": SMALL_PT,
    "legend.fontsize": SMALL_PT,
    "legend.title_fontsize": SMALL_PT,
    "lines.linewidth": 1.2,
    "lines.markersize": 4,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "grid.linewidth": 0.5,
    "svg.fonttype": "none",
    "savefig.dpi": 300,
}


def save(fig, stem: str) -> list[str]:
    """Write stem.png and stem.svg; returns the two paths."""
    paths = [f"{stem}.png", f"{stem}.svg"]
    for p in paths:
        fig.savefig(p)
    plt.close(fig)
    return paths
