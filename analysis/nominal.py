"""The nominal part (CAD) an inspection compares a measured cloud with: a triangle mesh in the
part's own frame (mm), with each triangle's CAD face and the faces' names.

- STEP goes through OpenCASCADE (``cadquery-ocp``): the file's length unit is read and
  converted to mm, the B-rep is tessellated with a stated chordal tolerance, and each face keeps
  the name its ``ADVANCED_FACE`` carries (how named face sets travel between CAD systems). The
  tessellation is kept on disk for the next load of the same geometry
  (:mod:`scancell.analysis.tessellation_cache`).
- STL, OBJ and PLY meshes go through trimesh (unprocessed: 0.2 s for the car rear's 358 k
  triangles, where Open3D's reader took 1.3 s); they carry no unit, so it is given (default mm).

Outward normals follow the triangles' winding (STEP: the faces' orientation); a deviation is
positive where material lies outside the nominal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: the smallest chordal tolerance relative to the part's diagonal (see _tessellate_step)
RELATIVE_CHORDAL = 2e-6
#: mm per unit
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4, "inch": 25.4, "ft": 304.8}
STEP_SUFFIXES = (".step", ".stp")
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".gltf", ".glb")
DEFAULT_CHORDAL_MM = 0.01
DEFAULT_ANGULAR_RAD = 0.3


class NominalError(ValueError):
    """The nominal cannot be loaded or does not fit the measurement."""


@dataclass
class Nominal:
    vertices: np.ndarray  # (V, 3) float64, part frame, mm
    triangles: np.ndarray  # (T, 3) int32, counter-clockwise seen from outside
    face_of_triangle: np.ndarray  # (T,) int32: index into face_names
    face_names: list[str]  # per CAD face ("" unnamed); one face for a plain mesh
    source: str
    unit: str  # the source's length unit
    chordal_tolerance_mm: float | None = None  # STEP tessellation
    _scene: Any = field(default=None, repr=False)
    #: the scene's triangle -> its triangle of :attr:`triangles` (None: the same triangles)
    _scene_parent: np.ndarray | None = field(default=None, repr=False)
    _normals: np.ndarray | None = field(default=None, repr=False)

    @property
    def triangle_normals(self) -> np.ndarray:
        """(T, 3) outward unit normals (computed once)."""
        if self._normals is None:
            v = self.vertices[self.triangles]
            n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            self._normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        return self._normals

    @property
    def area_mm2(self) -> float:
        v = self.vertices[self.triangles]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())

    @property
    def diagonal_mm(self) -> float:
        return float(np.linalg.norm(self.vertices.max(axis=0) - self.vertices.min(axis=0)))

    def faces_named(self, names: list[str]) -> np.ndarray:
        """Indices of the CAD faces with any of ``names``; an unknown name is an error."""
        known = {n for n in self.face_names if n}
        missing = [n for n in names if n not in known]
        if missing:
            raise NominalError(f"{self.source}: no face named {', '.join(map(repr, missing))} "
                               f"(named faces: {', '.join(sorted(known)) or 'none'})")
        return np.flatnonzero(np.isin(np.asarray(self.face_names, object), names))

    def scene(self):
        """Open3D's scene for closest points on the mesh (built once). Its thin triangles are
        cut first (:func:`scancell.analysis.mesh_refine.slice_thin_triangles`: Embree's float32
        closest point on a 3900 x 2.2 mm sliver is up to 1 mm off); :meth:`mesh_triangle`
        maps the scene's triangle ids back."""
        if self._scene is None:
            from scancell.analysis.mesh_refine import closest_point_scene

            self._scene, self._scene_parent = closest_point_scene(self.vertices, self.triangles)
        return self._scene

    def mesh_triangle(self, scene_ids: np.ndarray) -> np.ndarray:
        """The triangles of :attr:`triangles` (int32) that :meth:`scene`'s triangles
        ``scene_ids`` belong to."""
        ids = np.asarray(scene_ids).astype(np.int32, copy=False)
        return ids if self._scene_parent is None else self._scene_parent[ids]

    def legacy_mesh(self):
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                      o3d.utility.Vector3iVector(self.triangles))
        m.compute_triangle_normals()
        return m

    def describe(self) -> dict[str, Any]:
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        return {"source": self.source, "unit": self.unit, "triangles": len(self.triangles),
                "faces": len(self.face_names),
                "named_faces": sorted({n for n in self.face_names if n}),
                "chordal_tolerance_mm": self.chordal_tolerance_mm,
                "bbox_mm": [lo.round(3).tolist(), hi.round(3).tolist()],
                "area_mm2": round(self.area_mm2, 1)}


def load_nominal(path: str | Path, unit: str | None = None,
                 chordal_tolerance_mm: float = DEFAULT_CHORDAL_MM,
                 measured: np.ndarray | None = None) -> Nominal:
    """A STEP (unit read from the file) or a mesh (``unit`` given, default mm). With the
    ``measured`` cloud, a STEP whose size contradicts it is refused before it is tessellated
    (:func:`check_scale`)."""
    p = Path(path)
    if not p.is_file():
        raise NominalError(f"{p}: no such file")
    suffix = p.suffix.lower()
    if unit is not None and unit not in UNITS_MM:
        raise NominalError(f"unit {unit!r} unknown: use one of {', '.join(UNITS_MM)}")
    if suffix in STEP_SUFFIXES:
        if not chordal_tolerance_mm > 0:
            raise NominalError(f"chordal tolerance must be > 0 mm, got {chordal_tolerance_mm}")
        nominal = _load_step(p, chordal_tolerance_mm, measured)
        if unit is not None and UNITS_MM[unit] != UNITS_MM.get(nominal.unit, -1):
            raise NominalError(f"{p}: the STEP file states its unit as {nominal.unit!r}; "
                               f"the given unit {unit!r} contradicts it")
        return nominal
    if suffix in MESH_SUFFIXES:
        return _load_mesh(p, unit or "mm")
    raise NominalError(f"{p}: unknown nominal format {suffix!r} (STEP {', '.join(STEP_SUFFIXES)}; "
                       f"meshes {', '.join(MESH_SUFFIXES)})")


def _load_mesh(p: Path, unit: str) -> Nominal:
    import trimesh

    try:
        mesh = trimesh.load_mesh(str(p), process=False)
    except Exception as exc:  # trimesh raises what its format's parser raises
        raise NominalError(f"{p}: not a mesh trimesh can read ({exc})") from None
    if isinstance(mesh, trimesh.Scene):
        mesh = mesh.to_geometry() if mesh.geometry else None
    faces = getattr(mesh, "faces", None)
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), float)
    t = np.asarray(faces if faces is not None else np.zeros((0, 3)), np.int32)
    if len(t) == 0 or len(v) < 3:
        raise NominalError(f"{p}: no triangles (not a mesh, or an empty one)")
    if not np.isfinite(v).all():
        raise NominalError(f"{p}: vertices that are not finite numbers")
    return Nominal(v * UNITS_MM[unit], t, np.zeros(len(t), np.int32), [""], str(p), unit)


def quiet_opencascade() -> None:
    """OpenCASCADE prints its transfer statistics to stdout; keep only failures."""
    from OCP.Message import Message, Message_Gravity

    for printer in Message.DefaultMessenger_s().Printers():
        printer.SetTraceLevel(Message_Gravity.Message_Fail)


def _step_unit(reader) -> str:
    from OCP.collections import Sequence_TCollection_AsciiString

    length, angle, solid = (Sequence_TCollection_AsciiString() for _ in range(3))
    reader.FileUnits(length, angle, solid)
    names = [s.ToCString() for s in length]
    return {"millimetre": "mm", "metre": "m", "centimetre": "cm", "inch": "in",
            "foot": "ft"}.get(names[0] if names else "", names[0] if names else "mm")


def _load_step(p: Path, chordal_mm: float, measured: np.ndarray | None = None) -> Nominal:
    from scancell.analysis import tessellation_cache

    try:
        key = tessellation_cache.entry_key(p.read_bytes(), chordal_mm, DEFAULT_ANGULAR_RAD)
    except OSError as exc:
        raise NominalError(f"{p}: cannot read it ({exc.strerror or exc})") from None
    cached = tessellation_cache.read(key)
    if cached is not None:
        nominal = Nominal(cached["vertices"], cached["triangles"], cached["face_of_triangle"],
                          [str(n) for n in cached["face_names"]], str(p), str(cached["unit"]),
                          chordal_mm)
        if measured is not None:
            check_scale(nominal, measured)
        return nominal
    nominal = _tessellate_step(p, chordal_mm, measured)
    tessellation_cache.write(key, vertices=nominal.vertices, triangles=nominal.triangles,
                             face_of_triangle=nominal.face_of_triangle,
                             face_names=np.asarray(nominal.face_names, str),
                             unit=np.asarray(nominal.unit))
    return nominal


def _tessellate_step(p: Path, chordal_mm: float, measured: np.ndarray | None = None) -> Nominal:
    from OCP.Bnd import Bnd_Box
    from OCP.BRep import BRep_Tool
    from OCP.BRepBndLib import BRepBndLib
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.IFSelect import IFSelect_ReturnStatus
    from OCP.STEPControl import STEPControl_Reader
    from OCP.TopAbs import TopAbs_FACE, TopAbs_REVERSED
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS

    quiet_opencascade()
    reader = STEPControl_Reader()
    if reader.ReadFile(str(p)) != IFSelect_ReturnStatus.IFSelect_RetDone:
        raise NominalError(f"{p}: OpenCASCADE cannot read this STEP file (not STEP, or corrupt)")
    unit = _step_unit(reader)  # the reader converts to mm (xstep.cascade.unit)
    if reader.TransferRoots() == 0:
        raise NominalError(f"{p}: the STEP file has no shape OpenCASCADE can transfer")
    shape = reader.OneShape()
    box = Bnd_Box()
    BRepBndLib.Add_s(shape, box)
    if box.IsVoid():
        raise NominalError(f"{p}: the STEP file's shape is empty")
    lo, hi = box.CornerMin(), box.CornerMax()
    diagonal = float(np.linalg.norm([hi.X() - lo.X(), hi.Y() - lo.Y(), hi.Z() - lo.Z()]))
    if measured is not None:  # before the tessellation, which a wrong unit makes endless
        check_scale_of(diagonal, str(p), measured)
    # A smooth surface of curvature radius R tessellated at chordal tolerance c has of the order
    # of area / (R c) triangles: a tolerance that grows with the part (2 ppm of its diagonal)
    # keeps that count from growing with the part's scale; a 2.5 m car rear keeps 0.01 mm
    chordal_mm = max(chordal_mm, RELATIVE_CHORDAL * diagonal)
    BRepMesh_IncrementalMesh(shape, chordal_mm, False, DEFAULT_ANGULAR_RAD, True)
    transfer = reader.WS().TransferReader()
    verts, tris, faces, names = [], [], [], []
    offset = 0
    explorer = TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        face = TopoDS.Face(explorer.Current())
        explorer.Next()
        loc = TopLoc_Location()
        mesh = BRep_Tool.Triangulation_s(face, loc)
        if mesh is None or mesh.NbTriangles() == 0:
            continue
        entity = transfer.EntityFromShapeResult(face, 1)
        name = entity.Name().ToCString() if entity is not None and hasattr(entity, "Name") else ""
        trsf = loc.Transformation()
        v = np.array([[q.X(), q.Y(), q.Z()] for q in
                      (mesh.Node(i).Transformed(trsf) for i in range(1, mesh.NbNodes() + 1))])
        t = np.array([mesh.Triangle(i).Get() for i in range(1, mesh.NbTriangles() + 1)]) - 1
        if face.Orientation() == TopAbs_REVERSED:
            t = t[:, ::-1]
        verts.append(v)
        tris.append(t + offset)
        faces.append(np.full(len(t), len(names), np.int32))
        names.append("" if name in ("", "NONE") else name)
        offset += len(v)
    if not tris:
        raise NominalError(f"{p}: the STEP file has no faces to compare with (wireframe or "
                           f"points only?)")
    return Nominal(np.concatenate(verts), np.concatenate(tris).astype(np.int32),
                   np.concatenate(faces), names, str(p), unit, chordal_mm)


def check_scale(nominal: Nominal, points: np.ndarray) -> None:
    """A nominal in the wrong unit: the measured cloud is far larger (or smaller) than the part.
    A cloud may cover a small detail of a large part, so only a 5x larger cloud or a 200x
    smaller one is refused."""
    check_scale_of(nominal.diagonal_mm, nominal.source, points)


def thinned(points: np.ndarray, at_most: int = 1_000_000) -> np.ndarray:
    """Every k-th point, at most ``at_most`` of them (a view: no copy of a large cloud)."""
    return points[:: max(1, len(points) // at_most)]


def check_scale_of(diagonal_mm: float, source: str, points: np.ndarray) -> None:
    """:func:`check_scale` for a nominal of ``diagonal_mm`` across (mm), from a million of the
    points at most (:func:`thinned`: the extent of a 50 M-point cloud, without a copy of it)."""
    pts = np.asarray(thinned(np.asarray(points)), float)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 2:
        return
    lo, hi = np.percentile(pts, [1, 99], axis=0)
    ratio = float(np.linalg.norm(hi - lo)) / max(diagonal_mm, 1e-12)
    if 1 / 200 <= ratio <= 5:
        return
    times = max(ratio, 1 / ratio)
    factor = min((1000.0, 25.4, 10.0), key=lambda f: abs(np.log(times / f)))
    hint = {1000.0: "metres", 25.4: "inches", 10.0: "centimetres"}[factor]
    where = (f"is the nominal in {hint}? give its unit" if ratio > 1
             else f"was the nominal's unit given right, or is the cloud in {hint}?")
    raise NominalError(f"{source}: the nominal ({diagonal_mm:.4g} mm across) is "
                       f"{times:.0f}x {'smaller' if ratio > 1 else 'larger'} than the measured "
                       f"cloud: a wrong unit ({where}); no inspection made")
