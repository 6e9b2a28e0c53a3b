"""Drawing the ED-UAV association (the env's rgb_array render, the paper's Fig. 2, animations)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from uavlora_rllib.sim.association import UNASSOCIATED  # noqa: E402


def draw_association(
    ax,
    ed_xy: np.ndarray,
    uav_xy: np.ndarray,
    serving: np.ndarray,
    comm_range_m: float,
    area_m: float,
    title: str | None = None,
) -> None:
    """EDs (dots, coloured by serving UAV; grey crosses if unassociated), UAVs (triangles),
    R_comm circles and association lines, on axis `ax`."""
    colours = plt.get_cmap("tab10")
    for u, (x, y) in enumerate(uav_xy):
        c = colours(u % 10)
        ax.add_patch(plt.Circle((x, y), comm_range_m, fill=False, ls="--", lw=0.8, color=c, alpha=0.6))
        served = serving == u
        for ex, ey in ed_xy[served]:
            ax.plot([x, ex], [y, ey], color=c, lw=0.6, alpha=0.7)
        ax.scatter(ed_xy[served, 0], ed_xy[served, 1], s=14, color=c, zorder=3)
        ax.scatter([x], [y], marker="^", s=90, color=c, edgecolor="black", zorder=4, label=f"UAV {u}")
    lost = serving == UNASSOCIATED
    if lost.any():
        ax.scatter(ed_xy[lost, 0], ed_xy[lost, 1], marker="x", s=18, color="grey", zorder=3, label="unassociated")
    ax.set_xlim(0, area_m)
    ax.set_ylim(0, area_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title, fontsize=9)


def association_rgb(ed_xy, uav_xy, serving, comm_range_m, area_m, title=None, size_px: int = 480) -> np.ndarray:
    """The association map as an [H, W, 3] uint8 image."""
    dpi = 100
    fig, ax = plt.subplots(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    draw_association(ax, ed_xy, uav_xy, serving, comm_range_m, area_m, title)
    fig.tight_layout()
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return image
