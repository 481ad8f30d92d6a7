"""How many candidates the neighbour search tests per sphere, against the pairs it lists, on the
rained fill of one lab-geometry member (profile=lab, 50-50) at a sinter lobe spacing; and how
many a search on two grids would test (spheres up to a split radius on a grid of their own,
the larger ones querying every sphere on the coarse grid).

The column search of ``torchdem/_ext/cells_cpu.cpp`` bins spheres into columns one contact
distance of the largest sphere wide (2 r_max + skin) and scans, for sphere p, the neighbouring
columns within |dz| < r_p + r_max + skin (half stencil). With a wide size range (flat sinter
lobes of 2 mm beside pellets of 8 mm) most candidates are far from contact. Figures are counted
on the loose fill before it settles (packing about 0.3), so both counts are about half those of
a settled bed; their ratio is what the search pays.

Usage::

    python scripts/search_candidates.py [--lobe-spacing 0.3] [--seed 0] [--splits 0.4 0.5 0.6]
"""
from __future__ import annotations

import argparse

import numpy as np
from hydra import compose, initialize_config_dir
from scipy.spatial import cKDTree

from bo.cli.common import model_from, plain_config
from torchdem.cli import CONF_DIR
from torchdem.integrate import sphere_positions
from torchdem.errors import exit_on_bad_input


def column_candidates(x: np.ndarray, r: np.ndarray, query: np.ndarray, cell: float, reach_extra: float,
                      half: bool) -> float:
    """Candidates the spheres ``query`` (bool mask) test among all spheres of ``x``/``r``: the
    3 x 3 columns of edge ``cell`` around each, within |dz| < r_p + reach_extra; halved for a
    half stencil (each pair looked at once)."""
    ix, iy = np.floor(x[:, 0] / cell).astype(np.int64), np.floor(x[:, 1] / cell).astype(np.int64)
    columns: dict[tuple[int, int], np.ndarray] = {}
    order = np.lexsort((x[:, 2], iy, ix))
    keys = np.stack([ix[order], iy[order]], 1)
    cut = np.flatnonzero(np.any(np.diff(keys, axis=0) != 0, axis=1)) + 1
    for chunk in np.split(order, cut):
        columns[(int(ix[chunk[0]]), int(iy[chunk[0]]))] = np.sort(x[chunk, 2])
    total = 0
    q = np.flatnonzero(query)
    qx, qy = ix[q], iy[q]
    for key in set(zip(qx.tolist(), qy.tolist())):
        mine = q[(qx == key[0]) & (qy == key[1])]
        z, reach = x[mine, 2], r[mine] + reach_extra
        for da in (-1, 0, 1):
            for db in (-1, 0, 1):
                zo = columns.get((key[0] + da, key[1] + db))
                if zo is not None:
                    total += int((np.searchsorted(zo, z + reach) - np.searchsorted(zo, z - reach)).sum())
    return total / 2 if half else float(total)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lobe-spacing", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--splits", type=float, nargs="+", default=[0.4, 0.5, 0.6, 0.7],
                        help="split radii as fractions of the largest sphere radius")
    args = parser.parse_args()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("calibrate", overrides=["profile=lab"]))
    test = model_from(plain).test_for("50-50", [{"lobe_spacing_sinter": args.lobe_spacing}])
    system, state, _ = test.build([args.seed], [0])
    x = sphere_positions(system, state.bodies).double().numpy()
    r = system.sphere_radius.reshape(-1).double().numpy()
    body = system.sphere_body_flat.numpy()
    skin, r_max = float(system.skin), float(r.max())
    pairs = cKDTree(x).query_pairs(2 * r_max + skin, output_type="ndarray")
    d = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    listed = int(((d < r[pairs[:, 0]] + r[pairs[:, 1]] + skin) & (body[pairs[:, 0]] != body[pairs[:, 1]])).sum())
    every = np.ones(len(r), dtype=bool)
    now = column_candidates(x, r, every, 2 * r_max + skin, r_max + skin, half=True)
    print(f"lobe spacing {args.lobe_spacing}: {len(r)} spheres, radius {r.min() * 1e3:.2f}-{r_max * 1e3:.2f} mm "
          f"(median {np.median(r) * 1e3:.2f}), skin {skin * 1e3:.2f} mm")
    print(f"  listed pairs per sphere {2 * listed / len(r):.1f}; column search: {now / len(r):.1f} candidates per "
          f"sphere, {now / listed:.0f} per listed pair")
    for f in args.splits:
        split = f * r_max
        small = r <= split
        fine = column_candidates(x[small], r[small], np.ones(small.sum(), dtype=bool), 2 * split + skin,
                                 split + skin, half=True)
        coarse = column_candidates(x, r, ~small, 2 * r_max + skin, r_max + skin, half=False)
        print(f"  two grids split at {f:.2f} r_max ({small.sum()} small, {(~small).sum()} large): "
              f"{(fine + coarse) / len(r):.1f} candidates per sphere, {(fine + coarse) / now:.2f} of the column search")


if __name__ == "__main__":
    exit_on_bad_input("search_candidates.py", main)
