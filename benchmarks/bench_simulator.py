"""Throughput and peak memory of the scan simulator, and its ray caster against the one a
user would pick instead (trimesh with Intel Embree through embreex, on a triangulated copy of
the same scene), in one run. Each contender runs in its own process so peak RSS is its own.

    python benchmarks/bench_simulator.py [--scene street] [--points 5000000] [--rays 2000000]

- ``semantic3d.simulate``: the whole pipeline, rays cast, shaded and written as
  ``.txt`` + ``.labels`` (points/s);
- ``semantic3d.cast_rays``: nearest hits only, for the station's real sweep directions (rays/s);
- ``trimesh+embree intersects_first``: the same rays against the scene tessellated (boxes
  as 12 triangles, cylinders as 16-gon prisms, ellipsoids as 320-triangle icospheres,
  terrain as a 2 m triangle grid). Embree cannot express porous crowns, moving objects or the
  exact quadrics, so this measures raw casting speed only; agreement of hit/miss is printed.

The machine is shared: the load average is printed beside the numbers.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import OUT, Measurement, emit, measure_here, measure_in_child, table

HERE = Path(__file__).resolve()


def sweep_directions(scene_name: str, n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """Station 1's origin and the directions of a full sweep of about ``n_rays`` rays."""
    from semantic3d.datasets.simulator import Scanner, build_scene

    scanner = Scanner()
    station = build_scene(scene_name, seed=0).stations[0]
    step = math.sqrt(2 * math.pi * scanner.elevation_span_rad / n_rays)
    n_az = round(2 * math.pi / step)
    n_el = round(scanner.elevation_span_rad / step)
    azimuth = station.yaw_rad + np.arange(n_az) * (2 * math.pi / n_az)
    elevation = math.radians(scanner.elevation_min_deg) + (np.arange(n_el) + 0.5) * (
        scanner.elevation_span_rad / n_el
    )
    az, el = np.meshgrid(azimuth, elevation, indexing="ij")
    directions = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    return np.asarray(station.position), directions.reshape(-1, 3)


def tessellate(scene_name: str):  # type: ignore[no-untyped-def]
    """The scene as one triangle mesh (primitives at time 0, porous volumes as solids)."""
    import trimesh

    from semantic3d.datasets.simulator import Shape, build_scene

    scene = build_scene(scene_name, seed=0)
    meshes = []
    for prim in scene.primitives:
        hx, hy, hz = prim.half_size
        if prim.shape is Shape.BOX:
            mesh = trimesh.creation.box(extents=(2 * hx, 2 * hy, 2 * hz))
        elif prim.shape is Shape.CYLINDER:
            mesh = trimesh.creation.cylinder(radius=1.0, height=2 * hz, sections=16)
            mesh.apply_scale((hx, hy, 1.0))
        elif prim.shape is Shape.ELLIPSOID:
            mesh = trimesh.creation.icosphere(subdivisions=2)
            mesh.apply_scale((hx, hy, hz))
        else:  # gable prism
            v = [
                (-hx, -hy, -hz),
                (hx, -hy, -hz),
                (hx, hy, -hz),
                (-hx, hy, -hz),
                (-hx, 0, hz),
                (hx, 0, hz),
            ]
            f = [
                (0, 2, 1),
                (0, 3, 2),
                (0, 1, 5),
                (0, 5, 4),
                (3, 5, 2),
                (3, 4, 5),
                (0, 4, 3),
                (1, 2, 5),
            ]
            mesh = trimesh.Trimesh(v, f, process=False)
        transform = np.eye(4)
        transform[:3, :3] = prim.rotation()
        transform[:3, 3] = prim.center
        mesh.apply_transform(transform)
        meshes.append(mesh)
    grid = np.arange(-300.0, 300.1, 2.0)
    gx, gy = np.meshgrid(grid, grid, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), scene.terrain.height_at(gx, gy).ravel()], 1)
    n = len(grid)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
        idx[:-1, 1:].ravel(),
    )
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    meshes.append(trimesh.Trimesh(vertices, faces, process=False))
    return trimesh.util.concatenate(meshes)


def run_contender(name: str, scene_name: str, count: int) -> Measurement:
    if name == "semantic3d.simulate":
        from semantic3d.datasets.simulator import simulate

        out = OUT / "simulator"
        simulate(scene_name, out=out / "warm", n_points=10_000)  # load the compiled kernels
        try:
            return measure_here(
                name, lambda: simulate(scene_name, out=out / "run", n_points=count).n_points
            )
        finally:
            shutil.rmtree(out, ignore_errors=True)
    if name == "semantic3d.cast_rays":
        from semantic3d.datasets.simulator import build_scene, cast_rays, compile_scene

        origin, directions = sweep_directions(scene_name, count)
        compiled = compile_scene(build_scene(scene_name, seed=0))
        cast_rays(compiled, origin, directions[:1000])
        return measure_here(name, lambda: _cast_in_blocks(compiled, origin, directions))
    if name == "trimesh+embree intersects_first":
        origin, directions = sweep_directions(scene_name, count)
        mesh = tessellate(scene_name)
        if not mesh.ray.__class__.__module__.endswith("ray_pyembree"):
            raise SystemExit("trimesh is not using embree (pip install embreex)")
        mesh.ray.intersects_first(np.tile(origin, (10, 1)), directions[:10])  # build the BVH

        def cast() -> int:
            for start in range(0, len(directions), 1 << 20):
                block = directions[start : start + (1 << 20)]
                mesh.ray.intersects_first(np.broadcast_to(origin, block.shape), block)
            return len(directions)

        return measure_here(name, cast)
    raise SystemExit(f"unknown contender {name}")


def _cast_in_blocks(compiled, origin: np.ndarray, directions: np.ndarray) -> int:  # type: ignore[no-untyped-def]
    from semantic3d.datasets.simulator import cast_rays

    for start in range(0, len(directions), 1 << 20):
        cast_rays(compiled, origin, directions[start : start + (1 << 20)])
    return len(directions)


def agreement(scene_name: str, n_rays: int) -> str:
    """How often both casters agree on hit or miss (they differ on porous crowns, tessellation)."""
    from semantic3d.datasets.simulator import Scanner, build_scene, cast_rays

    origin, directions = sweep_directions(scene_name, n_rays)
    ours = cast_rays(
        build_scene(scene_name, seed=0), origin, directions, scanner=Scanner(max_range_m=1e4)
    )
    theirs = tessellate(scene_name).ray.intersects_first(
        np.broadcast_to(origin, directions.shape), directions
    )
    same = np.mean((ours.primitive != -2) == (theirs >= 0))
    return f"hit/miss agreement with embree on {len(directions):,} rays: {same:.1%}"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="street")
    parser.add_argument("--points", type=int, default=5_000_000)
    parser.add_argument("--rays", type=int, default=2_000_000)
    parser.add_argument("--only", choices=("simulate", "cast"), default=None)
    parser.add_argument("--child", nargs=3, metavar=("NAME", "SCENE", "COUNT"))
    args = parser.parse_args()
    if args.child:
        emit(run_contender(args.child[0], args.child[1], int(args.child[2])))
        return
    print(f"scene {args.scene}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    if args.only != "cast":
        started = time.perf_counter()
        sim = measure_in_child(HERE, "semantic3d.simulate", args.scene, str(args.points))
        print(
            table(
                "simulate: rays cast, shaded and written (.txt + .labels)",
                "points",
                [sim],
                sim.name,
            )
        )
        print(f"  ({time.perf_counter() - started:.0f} s with start-up)")
    if args.only != "simulate":
        rows = [measure_in_child(HERE, "semantic3d.cast_rays", args.scene, str(args.rays))]
        try:
            rows.append(
                measure_in_child(
                    HERE, "trimesh+embree intersects_first", args.scene, str(args.rays)
                )
            )
            print(agreement(args.scene, 200_000))
        except Exception as exc:
            print(f"trimesh+embree skipped: {exc}")
        print(table("nearest-hit ray casting, same rays", "rays", rows, "semantic3d.cast_rays"))


if __name__ == "__main__":
    main()
