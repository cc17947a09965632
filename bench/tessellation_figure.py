"""Figure: boundary tiers and Voronoi areas of a sampled 2D swarm, plain and periodic.

Run: python bench/tessellation_figure.py [--out bench/results/tessellation.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

import jaxgeom  # noqa: E402
from jaxgeom.apps._landscapes import sample_boltzmann  # noqa: E402

jax.config.update("jax_enable_x64", True)


def edges(tess):
    nbrs = np.asarray(tess.neighbors)
    i, k = np.nonzero(nbrs < tess.n_points)
    keep = i < nbrs[i, k]
    pts = np.asarray(tess.points)
    return np.stack([pts[i[keep]], pts[nbrs[i, k][keep]]], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=1500)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "tessellation.png")
    args = parser.parse_args()
    pts, box = sample_boltzmann("double_well", args.n, 2, beta=2.0, seed=1)
    tess = jaxgeom.delaunay(pts, box=box)
    uniform = np.random.default_rng(2).random((args.n, 2))
    torus = jaxgeom.delaunay(uniform, box=(0.0, 1.0), periodic=True)
    areas = np.asarray(jaxgeom.voronoi_volumes(torus))

    fig, axes = plt.subplots(1, 2, figsize=(13, 6))
    ax = axes[0]
    ax.add_collection(LineCollection(edges(tess), colors="0.8", linewidths=0.4))
    colours = np.array(["tab:red", "tab:orange", "tab:blue"])[np.asarray(tess.tier)]
    ax.scatter(pts[:, 0], pts[:, 1], c=colours, s=6)
    ax.set_title("exp(-2V) double well: tier 0 (red), 1 (orange), 2 (blue)")
    ax.set_aspect("equal")
    ax = axes[1]
    ax.add_collection(
        LineCollection(
            edges(torus)[np.all(np.abs(np.diff(edges(torus), axis=1)) < 0.5, axis=(1, 2))], colors="0.8", linewidths=0.4
        )
    )
    sc = ax.scatter(uniform[:, 0], uniform[:, 1], c=areas * args.n, s=8, cmap="viridis")
    fig.colorbar(sc, ax=ax, label="Voronoi area x N")
    ax.set_title(f"periodic unit box: sum of areas = {areas.sum():.12f}")
    ax.set_aspect("equal")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
