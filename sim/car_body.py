"""The simulated ``car_body``: a body-in-white-like solid of 4600 (y) x 1800 (x) x 1400 (z) mm,
built as a B-rep with OpenCASCADE so that its STEP and the surface the simulator renders are one
geometry.

Part frame: origin at the middle of the underbody, x across the car, y along it (+y the front),
z up (mm). The shape:

- the lower body, 780 mm high, its corners in plan rounded R 350, its top edges R 120 and its
  bottom edges R 40;
- the cabin, lofted from the belt line (1600 x 2500 mm) to the roof (1240 x 1300 mm): a raked
  windscreen and rear window, the sides leaning in (tumblehome), its edges R 90, blended into
  the lower body R 40;
- four wheel arches: cylinders R 340 cut 300 mm into each side at y = +-1450.

Each face carries a name in its STEP ``ADVANCED_FACE``: ``roof``, ``bonnet``, ``boot_lid``,
``windscreen``, ``rear_window``, ``side``, ``front``, ``rear``, ``wheel_arch``, ``underbody``
or ``blend`` (fillets and what joins the panels).

The simulator renders the STEP's own tessellation (``scancell.analysis.nominal``, chordal
tolerance 0.01 mm, cached on disk), so the truth a scan is scored against is the CAD within
that tolerance.
"""

from __future__ import annotations

import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np
import open3d as o3d

LENGTH_MM, WIDTH_MM, HEIGHT_MM = 4600.0, 1800.0, 1400.0
BELT_MM = 780.0
PLAN_CORNER_R, TOP_EDGE_R, BOTTOM_EDGE_R = 350.0, 120.0, 40.0
CABIN_BELT = (800.0, -1500.0, 1000.0)  # half width, rear y, front y at the belt line
CABIN_ROOF = (620.0, -1050.0, 250.0)  # the same at the roof (z = HEIGHT_MM)
CABIN_EDGE_R, CABIN_BLEND_R = 90.0, 40.0
ARCH_R, ARCH_Y, ARCH_CENTRE_Z, ARCH_DEPTH = 340.0, 1450.0, 60.0, 300.0
#: the surface the simulator renders: the STEP tessellated at this chordal tolerance
RENDER_CHORDAL_MM = 0.01


def _sub_shapes(shape, kind: str) -> list:
    """The shape's edges (``kind`` "edge") or faces ("face"), in OpenCASCADE's order."""
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    cast = TopoDS.Edge if kind == "edge" else TopoDS.Face
    out, ex = [], TopExp_Explorer(shape, TopAbs_EDGE if kind == "edge" else TopAbs_FACE)
    while ex.More():
        out.append(cast(ex.Current()))
        ex.Next()
    return out


def _edge_mid_and_direction(edge) -> tuple[np.ndarray, np.ndarray]:
    from OCP.BRepAdaptor import BRepAdaptor_Curve

    c = BRepAdaptor_Curve(edge)
    a, b = c.FirstParameter(), c.LastParameter()
    p0, p1, pm = c.Value(a), c.Value(b), c.Value(0.5 * (a + b))
    d = np.array([p1.X() - p0.X(), p1.Y() - p0.Y(), p1.Z() - p0.Z()])
    return np.array([pm.X(), pm.Y(), pm.Z()]), d / (np.linalg.norm(d) + 1e-12)


def _filleted(shape, radius_of) -> object:
    """``shape`` with each edge for which ``radius_of(mid, direction)`` gives a radius
    filleted to it."""
    from OCP.BRepFilletAPI import BRepFilletAPI_MakeFillet

    fillet = BRepFilletAPI_MakeFillet(shape)
    n = 0
    for e in _sub_shapes(shape, "edge"):
        r = radius_of(*_edge_mid_and_direction(e))
        if r:
            fillet.Add(float(r), e)
            n += 1
    fillet.Build()
    if n == 0 or not fillet.IsDone():
        raise RuntimeError(f"OpenCASCADE could not fillet the car body ({n} edges)")
    return fillet.Shape()


def _rectangle(half_x: float, y0: float, y1: float, z: float):
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakePolygon
    from OCP.gp import gp_Pnt

    p = BRepBuilderAPI_MakePolygon()
    for x, y in ((-half_x, y0), (half_x, y0), (half_x, y1), (-half_x, y1)):
        p.Add(gp_Pnt(x, y, z))
    p.Close()
    return p.Wire()


def car_body_solid():
    """The car body as an OpenCASCADE solid (part frame, mm)."""
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Cut, BRepAlgoAPI_Fuse
    from OCP.BRepOffsetAPI import BRepOffsetAPI_ThruSections
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox, BRepPrimAPI_MakeCylinder
    from OCP.gp import gp_Ax2, gp_Dir, gp_Pnt

    w, length = WIDTH_MM, LENGTH_MM
    lower = BRepPrimAPI_MakeBox(gp_Pnt(-w / 2, -length / 2, 0.0), w, length, BELT_MM).Shape()
    lower = _filleted(lower, lambda m, d: PLAN_CORNER_R if abs(d[2]) > 0.9 else None)
    lower = _filleted(lower, lambda m, d: TOP_EDGE_R if abs(m[2] - BELT_MM) < 1e-3
                      else BOTTOM_EDGE_R if abs(m[2]) < 1e-3 else None)
    loft = BRepOffsetAPI_ThruSections(True, True)
    loft.AddWire(_rectangle(CABIN_BELT[0], CABIN_BELT[1], CABIN_BELT[2], BELT_MM - 60.0))
    loft.AddWire(_rectangle(*CABIN_ROOF, HEIGHT_MM))
    loft.Build()
    cabin = _filleted(loft.Shape(), lambda m, d: CABIN_EDGE_R if m[2] > BELT_MM else None)
    body = BRepAlgoAPI_Fuse(lower, cabin).Shape()

    def on_the_belt(m: np.ndarray, d: np.ndarray):
        inside = abs(m[0]) <= CABIN_BELT[0] + 0.1 and CABIN_BELT[1] - 100 < m[1] < CABIN_BELT[2]
        return CABIN_BLEND_R if abs(m[2] - BELT_MM) < 30 and abs(d[2]) < 0.99 and inside else None

    body = _filleted(body, on_the_belt)
    for side in (-1.0, 1.0):
        x0 = WIDTH_MM / 2 - ARCH_DEPTH if side > 0 else -WIDTH_MM / 2 - 50.0  # 50 mm clear
        for y in (-ARCH_Y, ARCH_Y):
            cyl = BRepPrimAPI_MakeCylinder(gp_Ax2(gp_Pnt(x0, y, ARCH_CENTRE_Z), gp_Dir(1, 0, 0)),
                                           ARCH_R, ARCH_DEPTH + 50.0).Shape()
            body = BRepAlgoAPI_Cut(body, cyl).Shape()
    return body


def _face_name(face) -> str:
    """A face's name from where it lies and which way it faces (part frame)."""
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepGProp import BRepGProp
    from OCP.BRepLProp import BRepLProp_SLProps
    from OCP.GeomAbs import GeomAbs_BSplineSurface, GeomAbs_Cylinder, GeomAbs_Plane
    from OCP.GProp import GProp_GProps
    from OCP.TopAbs import TopAbs_REVERSED

    s = BRepAdaptor_Surface(face)
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, props)
    c = props.CentreOfMass()
    centre = np.array([c.X(), c.Y(), c.Z()])
    u = 0.5 * (s.FirstUParameter() + s.LastUParameter())
    v = 0.5 * (s.FirstVParameter() + s.LastVParameter())
    lp = BRepLProp_SLProps(s, u, v, 1, 1e-6)
    n = lp.Normal()
    normal = np.array([n.X(), n.Y(), n.Z()]) * (-1.0 if face.Orientation() == TopAbs_REVERSED
                                                 else 1.0)
    kind = s.GetType()
    if kind == GeomAbs_Cylinder and abs(s.Cylinder().Radius() - ARCH_R) < 1e-6:
        return "wheel_arch"
    if kind == GeomAbs_Plane and abs(normal[0]) > 0.99 and centre[2] < ARCH_CENTRE_Z + ARCH_R \
            and abs(abs(centre[0]) - (WIDTH_MM / 2 - ARCH_DEPTH)) < 1.0:
        return "wheel_arch"
    # the panels are planes, but the cabin's lofted ones come out of the fillet as B-splines
    panel = kind == GeomAbs_Plane or (kind == GeomAbs_BSplineSurface and props.Mass() > 3e5)
    if not panel:
        return "blend"
    if normal[2] < -0.9:
        return "underbody"
    if normal[2] > 0.99:
        return "roof" if centre[2] > BELT_MM + 1 else "bonnet" if centre[1] > 0 else "boot_lid"
    if abs(normal[0]) > abs(normal[1]):
        return "side"
    if normal[2] > 0.2:
        return "windscreen" if normal[1] > 0 else "rear_window"
    return "front" if normal[1] > 0 else "rear"


def car_body_shape():
    """The solid and, per face, its name (for :func:`scancell.sim.cad.write_step`)."""
    solid = car_body_solid()
    return solid, [(f, _face_name(f)) for f in _sub_shapes(solid, "face")]


@lru_cache(maxsize=1)
def _render_arrays() -> tuple[np.ndarray, np.ndarray]:
    from scancell.analysis.nominal import load_nominal
    from scancell.sim.cad import write_step

    with tempfile.TemporaryDirectory(prefix="scancell-car-body-") as tmp:
        shape, named = car_body_shape()
        step = write_step(Path(tmp) / "car_body.step", shape, named, "car_body")
        nominal = load_nominal(step, chordal_tolerance_mm=RENDER_CHORDAL_MM)
    return nominal.vertices, nominal.triangles


def car_body() -> o3d.geometry.TriangleMesh:
    """The car body's surface as the simulator renders it (part frame, mm): its STEP's
    tessellation, outward normals."""
    v, t = _render_arrays()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    m.compute_triangle_normals()
    return m
