"""Scene files (GLB, glTF, OBJ, PLY) to ``Scene``, through trimesh.

Triangle ids are the rows of the face array in the order trimesh loads the file with
``process=False`` (a scene's meshes concatenated in scene-graph order), so anyone holding the file
can check them. Coordinates are normalised to Y-up metres: file units times the sidecar's
``scale``. A sidecar ``<stem>.json`` beside the file may give:

- ``"scale"``: metres per file unit (default 1);
- ``"up"``: ``"y"`` (default) or ``"z"`` for Z-up files (rotated to Y-up, right-handed);
- ``"walk"``: ``{"rects": [[x0, z0, x1, z1, floor_y], ...], "eye_height": ..., "eye_range":
  [lo, hi]}`` in metres, overriding the walk area detected from the geometry;
- ``"cell_size"``: the default viewcell size in metres for this scene;
- ``"winding"``: ``"ccw"`` (default, glTF's rule) or ``"cw"`` when front faces wind clockwise
  (walk detection reads floors from normals);
- ``"eye_height"``, ``"eye_range"``: metres above the floor for detected walk areas.

Public scenes whose sidecar we cannot edit get the same keys from ``visibility/scene_hints/``
(a hint applies only to a file of that stem whose triangle count matches the hint's).

Degenerate faces (zero area, NaN/inf vertices, repeated indices) are kept in the face array (ids
stay stable) and reported; ``Scene.valid_faces`` keeps them out of computation.
"""

from __future__ import annotations

import gc
import json
import logging
import os
import re
from pathlib import Path

import numpy as np

from visibility.scene import Scene, WalkArea

log = logging.getLogger(__name__)

#: File extensions the loader accepts (lower case).
SCENE_EXTENSIONS = (".glb", ".gltf", ".obj", ".ply")

#: Colour for faces whose file has none (light grey).
DEFAULT_COLOR = (200, 200, 200)


#: Most triangles a scene file may hold (``load_scene``'s default ``max_triangles``): 8 times
#: the largest real scene (kitchen's 1M). What a loaded triangle costs, at the peak of a load
#: and once loaded, is measured by ``benchmarks/bench_memory.py`` (docs/memory.md). Past the
#: limit a file is refused before it is parsed (counts read from the PLY header, the glTF JSON,
#: OBJ face lines).
MAX_TRIANGLES = 1 << 23
#: Largest scene file read (``load_scene``'s default ``max_bytes``): 1 GiB, 45 times kitchen.glb
#: (22 MB); trimesh reads a file whole, so its size is memory.
MAX_FILE_BYTES = 1 << 30
#: Largest glTF JSON (and PLY header) parsed to count triangles before loading, bytes.
_MAX_HEADER_BYTES = 64 << 20


class SceneLoadError(ValueError):
    """A scene file that cannot be turned into a Scene (missing, unsupported, no triangles,
    over a size limit). Messages name the file, never its folder (``strip_paths``): a server
    shows them to clients."""


class SceneTooLarge(SceneLoadError):
    """A scene file over a size limit of ``load_scene``.

    Attributes
    ----------
    file : str, the file's name (no folder).
    detail : str, what the file is, e.g. "declares 9000000 triangles" or "is 5000 bytes".
    limit : int, the limit it is over, in the unit ``detail`` names (triangles or bytes).
    param : str or None, the ``load_scene`` argument that set the limit ("max_triangles",
        "max_bytes"); None for the loader's own fixed limits (a glTF JSON's size).
    """

    def __init__(self, file: str, detail: str, limit: int, param: str | None) -> None:
        super().__init__(f"{file} {detail}, over the limit of {limit}"
                         + (f" ({param})" if param else ""))
        self.file, self.detail, self.limit, self.param = file, detail, int(limit), param


#: An absolute POSIX path's folders: a "/" that starts no word of a relative path or a unit
#: ("m/s", "a/b"), then one or more "name/" parts, up to the last name.
_FOLDERS = re.compile(r"(?<![\w.])/(?:[^/\s'\"]+/)+")


def strip_paths(text: str, *folders: str | os.PathLike | None) -> str:
    """``text`` without file-system folders, for messages shown to clients (an exception's
    text may quote the path it failed on).

    Parameters
    ----------
    text : the message.
    folders : folders known to appear (relative ones included), as given and resolved; None
        entries are skipped. Any other absolute path loses its folders by shape.

    Returns
    -------
    str, ``text`` where every path is reduced to its file name.
    """
    for folder in folders:
        if folder is None:
            continue
        for form in {str(folder), str(Path(folder).resolve())}:
            if form not in ("", "/", "."):
                text = text.replace(form.rstrip("/") + "/", "")
    return _FOLDERS.sub("", text)


def _gltf_triangles(doc: dict) -> int:
    """Triangles a glTF document draws: per node with a mesh, its primitives' index (or vertex)
    counts / 3 (triangle modes 4, 5, 6: count - 2 for strips and fans)."""
    acc = doc.get("accessors") or []
    meshes = doc.get("meshes") or []

    def count(i) -> int:
        return int(acc[i].get("count", 0)) if isinstance(i, int) and 0 <= i < len(acc) else 0

    per_mesh = []
    for mesh in meshes:
        total = 0
        for prim in (mesh or {}).get("primitives") or []:
            mode = prim.get("mode", 4)
            n = count(prim["indices"]) if "indices" in prim else \
                count((prim.get("attributes") or {}).get("POSITION"))
            total += n // 3 if mode == 4 else max(n - 2, 0) if mode in (5, 6) else 0
        per_mesh.append(total)
    nodes = [nd.get("mesh") for nd in doc.get("nodes") or [] if isinstance(nd, dict)]
    used = [m for m in nodes if isinstance(m, int) and 0 <= m < len(per_mesh)]
    return sum(per_mesh[m] for m in used) if used else sum(per_mesh)


def count_triangles(path: str | Path) -> int | None:
    """Triangles a scene file declares, read without loading it (PLY header faces, glTF/GLB
    JSON accessors, OBJ face lines streamed), or None when the file does not say. A file
    built to lie only gets as far as the count after loading (``load_scene`` checks both)."""
    path = Path(path)
    ext = path.suffix.lower()
    try:
        with path.open("rb") as fh:
            if ext == ".ply":
                head = fh.read(_MAX_HEADER_BYTES // 64).split(b"end_header", 1)[0]
                for line in head.decode("ascii", "replace").splitlines():
                    parts = line.split()
                    if len(parts) == 3 and parts[:2] == ["element", "face"]:
                        return int(parts[2])
                return None
            if ext == ".glb":
                header = fh.read(20)
                if len(header) < 20 or header[:4] != b"glTF" or header[16:20] != b"JSON":
                    return None
                size = int.from_bytes(header[12:16], "little")
                if size > _MAX_HEADER_BYTES:
                    raise SceneTooLarge(path.name, f"has a glTF JSON of {size} bytes",
                                        _MAX_HEADER_BYTES, None)
                return _gltf_triangles(json.loads(fh.read(size)))
            if ext == ".gltf":
                size = path.stat().st_size
                if size > _MAX_HEADER_BYTES:
                    raise SceneTooLarge(path.name, f"is a glTF JSON of {size} bytes",
                                        _MAX_HEADER_BYTES, None)
                return _gltf_triangles(json.loads(fh.read()))
            if ext == ".obj":
                total = 0
                for line in fh:
                    if line.startswith(b"f ") or line.startswith(b"f\t"):
                        total += max(len(line.split()) - 3, 0)
                return total
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        if isinstance(exc, SceneLoadError):
            raise
        log.debug("could not count the triangles of %s: %s", path.name, exc)
    return None


HINTS_DIR = Path(__file__).resolve().parent / "scene_hints"


def read_hints(path: str | Path, triangles: int) -> dict:
    """Bundled hints for a known public scene file ({} when none match its stem and size)."""
    hint = HINTS_DIR / f"{Path(path).stem}.json"
    if not hint.is_file():
        return {}
    data = json.loads(hint.read_text())
    if int(data.get("triangles", -1)) != int(triangles):
        return {}
    return data


def read_sidecar(path: str | Path) -> dict:
    """The ``<stem>.json`` sidecar beside a scene file as a dict ({} when there is none)."""
    side = Path(path).with_suffix(".json")
    if not side.is_file():
        return {}
    try:
        data = json.loads(side.read_text())
    except OSError as exc:
        # strerror, not str(exc): the latter quotes the full path.
        raise SceneLoadError(f"unreadable sidecar {side.name}: {exc.strerror or exc}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneLoadError(f"sidecar {side.name} is not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise SceneLoadError(f"sidecar {side.name} must hold a JSON object")
    return data


def _face_colors(mesh) -> np.ndarray:
    """(m, 3) uint8 per-face colour: the first corner's vertex colour, else the material's."""
    m = len(mesh.faces)
    visual = mesh.visual
    try:
        if visual.kind == "vertex":
            vc = np.asarray(visual.vertex_colors)
            return vc[mesh.faces[:, 0], :3].astype(np.uint8)
        if visual.kind == "face":
            return np.asarray(visual.face_colors)[:, :3].astype(np.uint8)
        if visual.kind == "texture":
            mat = getattr(visual, "material", None)
            color = getattr(mat, "baseColorFactor", None)
            if color is None:
                color = getattr(mat, "main_color", None)
            if color is not None:
                c = np.asarray(color, dtype=np.float64)[:3]
                if c.max() <= 1.0:
                    c = c * 255.0
                return np.tile(np.clip(c, 0, 255).astype(np.uint8), (m, 1))
    except (AttributeError, IndexError, ValueError) as exc:
        log.debug("no usable colours (%s); using the default", exc)
    return np.tile(np.array(DEFAULT_COLOR, dtype=np.uint8), (m, 1))


def load_scene(path: str | Path, scale: float | None = None, name: str | None = None,
               max_triangles: int = MAX_TRIANGLES, max_bytes: int = MAX_FILE_BYTES) -> Scene:
    """Load a GLB/glTF/OBJ/PLY file as a Scene in Y-up metres.

    Parameters
    ----------
    path : the scene file.
    scale : metres per file unit; overrides the sidecar's ``"scale"`` (default 1).
    name : the scene's name (default: the file stem).
    max_triangles : refuse (``SceneTooLarge`` naming the limit) a file declaring or holding
        more triangles; checked before parsing where the format says (``count_triangles``).
    max_bytes : refuse (``SceneTooLarge``) a larger file, bytes, without reading it.

    Raises SceneLoadError (SceneTooLarge over a limit), whose message names the file but not
    its folder.

    Object ids: a custom ``_OBJECT_ID`` vertex attribute when the file has one (per face, the
    first corner's), otherwise one id per mesh instance in scene-graph order.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise SceneLoadError(f"no scene file {path.name!r}")
    if path.suffix.lower() not in SCENE_EXTENSIONS:
        raise SceneLoadError(f"unsupported scene format {path.suffix!r}; use {SCENE_EXTENSIONS}")
    size = path.stat().st_size
    if size > max_bytes:
        raise SceneTooLarge(path.name, f"is {size} bytes", max_bytes, "max_bytes")
    declared = count_triangles(path)
    if declared is not None and declared > max_triangles:
        raise SceneTooLarge(path.name, f"declares {declared} triangles", max_triangles,
                            "max_triangles")
    side = read_sidecar(path)
    if scale is None:
        scale = float(side.get("scale", 1.0))
    if not (np.isfinite(scale) and scale > 0):
        raise SceneLoadError(f"scale must be a positive number, got {scale}")
    try:
        tscene = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        reason = strip_paths(str(exc), path.parent) or type(exc).__name__
        raise SceneLoadError(f"cannot read {path.name}: {reason}") from exc
    parts = [g for g in tscene.dump(concatenate=False) if hasattr(g, "faces") and len(g.faces)]
    # The dumped parts are transformed copies: trimesh's own scene is no longer needed.
    del tscene
    if not parts:
        raise SceneLoadError(f"{path.name} holds no triangles")
    held = sum(len(g.faces) for g in parts)
    if held > max_triangles:
        raise SceneTooLarge(path.name, f"holds {held} triangles", max_triangles,
                            "max_triangles")
    # The scene's arrays are allocated once in their final dtypes and filled part by part, each
    # part released as soon as it is copied: no concatenated int64 or float64 copies.
    vertices = np.empty((sum(len(g.vertices) for g in parts), 3))
    faces = np.empty((held, 3), dtype=np.int32)
    objs = np.empty(held, dtype=np.int32)
    cols = np.empty((held, 3), dtype=np.uint8)
    names: list[str] = []
    offset = first = 0
    next_obj = 0
    for k in range(len(parts)):
        g, parts[k] = parts[k], None
        v = np.asarray(g.vertices, dtype=np.float64)
        f = np.asarray(g.faces, dtype=np.int64)
        nv, m = len(v), len(f)
        np.multiply(v, scale, out=vertices[offset:offset + nv])
        # Indices past int32 wrap, as an int32 cast wraps them (such faces are out of range).
        np.add(f, offset, out=faces[first:first + m], casting="unsafe")
        cols[first:first + m] = _face_colors(g)
        attr = getattr(g, "vertex_attributes", {}).get("_OBJECT_ID")
        if attr is not None and len(attr) == nv:
            local = np.asarray(attr).reshape(nv, -1)[:, 0].astype(np.int64)[f[:, 0]]
            objs[first:first + m] = local + next_obj
            obj_names = g.metadata.get("object_names") if hasattr(g, "metadata") else None
            n_local = int(local.max()) + 1 if len(local) else 0
            if isinstance(obj_names, (list, tuple)) and len(obj_names) >= n_local:
                names.extend(str(s) for s in obj_names[:n_local])
            else:
                names.extend(f"{path.stem}#{k}.{i}" for i in range(n_local))
            next_obj += n_local
        else:
            objs[first:first + m] = next_obj
            names.append(str(g.metadata.get("name", f"{path.stem}#{k}")))
            next_obj += 1
        offset += nv
        first += m
        del g, v, f
    # trimesh's meshes hold reference cycles (mesh <-> visuals, caches): only the cycle
    # collector frees their arrays, so run it now rather than at some later allocation.
    gc.collect()
    if str(side.get("up", "y")).lower() == "z":
        # Z-up to Y-up, right-handed: (x, y, z) -> (x, z, -y), in place.
        y = vertices[:, 1].copy()
        vertices[:, 1] = vertices[:, 2]
        np.negative(y, out=vertices[:, 2])
        del y
    side = {**read_hints(path, held), **side}
    walk = None
    if "walk" in side:
        w = side["walk"]
        walk = WalkArea(
            rects=np.asarray(w["rects"], dtype=np.float64),
            eye_height=float(w.get("eye_height", 1.7)),
            eye_range=tuple(w.get("eye_range", (1.5, 1.9))),
        )
    scene = Scene(
        vertices=vertices,
        faces=faces,
        object_ids=objs,
        colors=cols,
        name=name or path.stem,
        walk=walk,
        object_names=names,
        meta={
            "source": str(path),
            "scale": scale,
            "cell_size": side.get("cell_size"),
            "is_2_5d": side.get("is_2_5d"),
            "winding": side.get("winding", "ccw"),
            "eye_height": side.get("eye_height"),
            "eye_range": side.get("eye_range"),
        },
    )
    rep = scene.degenerate_report
    if rep.total_reasons:
        log.warning(
            "%s: %d faces kept out of computation: %s",
            path.name,
            scene.n_triangles - int(scene.valid_faces.sum()),
            rep.as_dict(),
        )
    return scene
