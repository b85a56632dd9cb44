"""A finished run's folder read back as a map: a versioned manifest, integrity checks, typed records.

Every run with the back-end that finishes (not one that fails, and not a localisation-only run) ends by
writing ``map.json`` (last, atomically): the format name and
version, the number of submaps, and the size of every file the map needs (``graph.json``,
``config.json``, ``submaps/NNNNNN.npy``, the points of each submap in its own frame, and
``submaps/NNNNNN.rgb.npy``, their image colours, and ``submaps/NNNNNN.landmarks.npz``, their appearance
landmarks, where the run had them). A folder is a
map only once that manifest exists, so an interrupted run is not mistaken for one. :func:`load_map`
refuses, in one line, a folder without a manifest, another format or version, and a missing or
truncated file; it reads the pose graph into a :class:`SavedMap` and leaves the points on disk.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vggt_slam_pp.backend.graph import Edge
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.errors import InputError
from vggt_slam_pp.io.trajectory import atomic_write_text

MAP_FORMAT = "vggt-slam-pp map"
MAP_VERSION = 1


@dataclass(frozen=True, eq=False)
class SavedSubmap:
    id: int
    frames: np.ndarray  # [S] source frame indices of its keyframes (of the recording that made it)
    T_world_submap: np.ndarray  # [4,4] optimised pose
    camera_centers: np.ndarray  # [S,3] its keyframes' camera centres, submap frame
    placed: bool = True  # in the map's frame (False: a recording no loop has placed in it yet)


@dataclass(frozen=True, eq=False)
class SavedMap:
    """A map on disk: submaps in id order, the graph's odometry and accepted loop edges, the DEM plane."""

    folder: Path
    submaps: list[SavedSubmap]
    edges: list[Edge]
    plane: dict
    tile_size: float
    config: dict  # the RunConfig (as a dictionary) of the run that made it

    @property
    def store(self) -> SubmapStore:
        return SubmapStore(self.folder / "submaps", cache_size=0)


def _manifest_files(folder: Path, n_submaps: int) -> list[str]:
    return ["graph.json", "config.json", *(f"submaps/{i:06d}.npy" for i in range(n_submaps))]


def write_manifest(folder: str | Path, n_submaps: int) -> None:
    """Write ``map.json`` for a finished run in ``folder`` (after every file it lists)."""
    folder = Path(folder)
    names = _manifest_files(folder, n_submaps)
    names += [f"submaps/{i:06d}.{kind}" for kind in ("rgb.npy", "landmarks.npz") for i in range(n_submaps)
              if (folder / f"submaps/{i:06d}.{kind}").is_file()]
    files = {name: (folder / name).stat().st_size for name in names}
    manifest = {"format": MAP_FORMAT, "version": MAP_VERSION, "submaps": n_submaps, "files": files}
    atomic_write_text(folder / "map.json", json.dumps(manifest, indent=1))


def _edge(d: dict) -> Edge:
    info = {k: v for k, v in d.items() if k not in ("from", "to", "kind", "T", "sigmas", "information")}
    information = np.asarray(d["information"], float) if d.get("information") is not None else None
    return Edge(int(d["from"]), int(d["to"]), np.asarray(d["T"], float), np.asarray(d["sigmas"], float), d["kind"],
                info, information)


def load_map(folder: str | Path) -> SavedMap:
    """Read the map in ``folder`` (see the module docstring); one-line :class:`InputError` otherwise."""
    folder = Path(folder)
    try:
        manifest = json.loads((folder / "map.json").read_text())
    except FileNotFoundError:
        raise InputError(f"{folder} is not a map: no map.json (a run with the back-end writes it when it "
                         "finishes)") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{folder}/map.json is damaged: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != MAP_FORMAT:
        raise InputError(f"{folder}/map.json is not a {MAP_FORMAT} manifest")
    if manifest.get("version") != MAP_VERSION:
        raise InputError(f"{folder} is a map of format version {manifest.get('version')}; this version of "
                         f"vggt-slam-pp reads version {MAP_VERSION}")
    files, n = manifest.get("files"), manifest.get("submaps")
    if not isinstance(files, dict) or not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise InputError(f"{folder}/map.json is damaged: it must list its files and a submap count")
    for name in dict.fromkeys([*_manifest_files(folder, n), *files]):  # colours and landmarks are listed when stored
        path = folder / name
        if name not in files or not path.is_file():
            raise InputError(f"damaged map {folder}: {name} is missing")
        if path.stat().st_size != files[name]:
            raise InputError(f"damaged map {folder}: {name} has {path.stat().st_size} bytes, the manifest says "
                             f"{files[name]}")
    try:
        graph = json.loads((folder / "graph.json").read_text())
        config = json.loads((folder / "config.json").read_text())
        submaps = [SavedSubmap(int(d["id"]), np.asarray(d["frames"], np.int64), np.asarray(d["T_world_submap"], float),
                               np.asarray(d["camera_centers"], float).reshape(-1, 3), bool(d.get("placed", True)))
                   for d in graph["nodes"]]
        edges = [_edge(d) for d in graph["edges"]]
        plane, tile_size = graph["plane"], float(graph["tile_size"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"damaged map {folder}: graph.json or config.json cannot be read ({exc})") from None
    if [s.id for s in submaps] != list(range(n)):
        raise InputError(f"damaged map {folder}: graph.json has submaps {[s.id for s in submaps][:5]}..., the "
                         f"manifest {n}")
    return SavedMap(folder, submaps, edges, plane, tile_size, config)
