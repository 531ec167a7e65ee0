"""A library of CAD models by name (``models/objects/`` by default).

The folder is indexed once when the library is created: every ``.stl``,
``.obj``, ``.ply`` or ViSP ``.cao`` file is a model named by its file stem. Models (and their
BSP trees) are loaded on first use and cached for the library's lifetime.
:func:`object_mesh_path` turns an object as the commands take it (a name here, or a
model file) into a validated file in metres.
"""

from __future__ import annotations

import threading
from pathlib import Path

from vespro.bsp import BSPTree, load_or_build_bsp
from vespro.model import Model, ModelError, load_model, model_file_in_metres

__all__ = ["ModelLibrary", "DEFAULT_ROOT", "object_mesh_path"]

#: The project's own models.
DEFAULT_ROOT = Path(__file__).resolve().parents[1] / "models" / "objects"

_SUFFIXES = (".stl", ".obj", ".ply", ".cao")


class ModelLibrary:
    """Models in one folder, by name.

    Parameters
    ----------
    root : str or Path, optional
        Folder of model files; defaults to the project's ``models/objects``.
    unit : str
        CAD unit of the files (see ``vespro.model.UNIT_SCALE``); all files of
        one library share it.
    cache_dir : str or Path, optional
        BSP cache folder (``vespro.bsp.default_cache_dir()`` if None).

    Raises
    ------
    FileNotFoundError
        ``root`` is not a folder.
    ValueError
        Two files with the same stem (``box.stl`` and ``box.obj``).
    """

    def __init__(self, root=None, unit: str = "m", cache_dir=None):
        self.root = Path(root) if root is not None else DEFAULT_ROOT
        if not self.root.is_dir():
            raise FileNotFoundError(f"model library folder not found: {self.root}")
        self.unit = unit
        self.cache_dir = cache_dir
        paths: dict[str, Path] = {}
        for p in sorted(self.root.iterdir()):
            if p.is_file() and p.suffix.lower() in _SUFFIXES:
                if p.stem in paths:
                    raise ValueError(f"two model files named {p.stem!r}: {paths[p.stem].name} and {p.name}")
                paths[p.stem] = p
        self._paths = paths
        self._models: dict[str, Model] = {}
        self._trees: dict[str, BSPTree] = {}
        self._lock = threading.Lock()

    @property
    def names(self) -> tuple:
        """Model names, sorted."""
        return tuple(self._paths)

    def path(self, name: str) -> Path:
        """File of model ``name``; ``KeyError`` listing the names if unknown."""
        try:
            return self._paths[name]
        except KeyError:
            raise KeyError(f"no model {name!r} in {self.root}; have {list(self._paths)}") from None

    def load(self, name: str) -> Model:
        """The validated model ``name`` (loaded once, then cached)."""
        with self._lock:
            m = self._models.get(name)
            if m is None:
                m = load_model(self.path(name), unit=self.unit, name=name)
                self._models[name] = m
            return m

    def tree(self, name: str) -> BSPTree:
        """The BSP tree of model ``name`` (disk-cached by content hash, then kept)."""
        model = self.load(name)
        with self._lock:
            t = self._trees.get(name)
            if t is None:
                t = load_or_build_bsp(model, cache_dir=self.cache_dir)
                self._trees[name] = t
            return t

    def __contains__(self, name: str) -> bool:
        return name in self._paths

    def __repr__(self) -> str:
        return f"ModelLibrary({str(self.root)!r}, names={list(self._paths)})"


def object_mesh_path(name_or_path: str, unit: str = "m") -> Path:
    """A validated CAD file in metres: a model name in ``models/objects``, or a file path.

    A file drawn in ``unit`` is checked (closed, outward, a plausible size) and,
    unless it is already an STL, OBJ or PLY in metres, converted to one
    (``vespro.model.model_file_in_metres``).
    """
    p = Path(name_or_path)
    if p.is_file():
        return model_file_in_metres(p, unit)
    lib = ModelLibrary()
    if name_or_path in lib.names:
        return model_file_in_metres(lib.path(name_or_path), lib.unit)
    raise ModelError(f"no object {name_or_path!r}; known objects: {', '.join(lib.names)} (or give a mesh path)")
