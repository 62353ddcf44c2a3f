"""The simulated part's nominal CAD: a STEP solid model and an STL of the car rear, for
``scancell inspect --nominal``.

The STEP is a shell of B-spline faces approximating :func:`scancell.sim.parts.car_rear_depth`
within 1 µm (OpenCASCADE's ``GeomAPI_PointsToBSplineSurface``), split along the feature-line
crease and around the licence-plate recess, and sewn. Each face carries its name in the STEP
``ADVANCED_FACE`` (``body``, ``bumper``, ``plate``, ``plate_walls``), which is how named face
sets travel between CAD systems. Outward normals face -x, towards the viewer, as the simulated
part's mesh does. The STL is the simulated part's own mesh (2 mm facets).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scancell.analysis.nominal import quiet_opencascade
from scancell.sim import parts
from scancell.sim.car_body import car_body_shape

#: breaks of the B-spline patches: the plate recess's body edges and the crease at z = -120
_Y_BREAKS = (parts.CAR_REAR_Y[0], *parts.PLATE_BODY_EDGES[0], parts.CAR_REAR_Y[1])
_Z_BREAKS = (parts.CAR_REAR_Z[0], *parts.PLATE_BODY_EDGES[1], -120.0, parts.CAR_REAR_Z[1])
SAMPLE_STEP_MM = 2.5
FIT_TOLERANCE_MM = 1e-3


def _patch(y: tuple[float, float], z: tuple[float, float]):
    """A B-spline surface through x = car_rear_depth(y, z) over a (y, z) rectangle; u runs
    along z and v along y, so that du x dv faces -x."""
    from OCP.collections import Array2_gp_Pnt
    from OCP.GeomAbs import GeomAbs_C2
    from OCP.GeomAPI import GeomAPI_PointsToBSplineSurface
    from OCP.gp import gp_Pnt

    ny = max(int(np.ceil((y[1] - y[0]) / SAMPLE_STEP_MM)), 3) + 1
    nz = max(int(np.ceil((z[1] - z[0]) / SAMPLE_STEP_MM)), 3) + 1
    ys, zs = np.linspace(*y, ny), np.linspace(*z, nz)
    Y, Z = np.meshgrid(ys, zs)
    X = parts.car_rear_depth(Y, Z)
    grid = Array2_gp_Pnt(1, nz, 1, ny)
    for i in range(nz):
        for j in range(ny):
            grid.SetValue(i + 1, j + 1, gp_Pnt(float(X[i, j]), float(ys[j]), float(zs[i])))
    return GeomAPI_PointsToBSplineSurface(grid, 3, 8, GeomAbs_C2, FIT_TOLERANCE_MM).Surface()


def _iso(surface, side: str):
    u0, u1, v0, v1 = surface.Bounds()
    return {"u0": lambda: surface.UIso(u0), "u1": lambda: surface.UIso(u1),
            "v0": lambda: surface.VIso(v0), "v1": lambda: surface.VIso(v1)}[side]()


def car_rear_faces() -> list[tuple[object, str]]:
    """(Geom surface, face name) of the car rear: 11 body/bumper patches, the plate, its 4
    walls (ruled between the body's edge and the plate's)."""
    from OCP.GeomFill import GeomFill

    faces: list[tuple[object, str]] = []
    cells = {}
    for a in range(3):
        for b in range(4):
            if (a, b) == (1, 1):
                continue  # the recess
            s = _patch(_Y_BREAKS[a:a + 2], _Z_BREAKS[b:b + 2])
            cells[a, b] = s
            faces.append((s, "body" if _Z_BREAKS[b] >= -120.0 else "bumper"))
    plate = _patch(*parts.PLATE_FLOOR_EDGES)
    faces.append((plate, "plate"))
    # (body patch beside the recess, its edge on the recess, the plate's edge facing it)
    for cell, body_side, plate_side in (((0, 1), "v1", "v0"), ((2, 1), "v0", "v1"),
                                        ((1, 2), "u0", "u1"), ((1, 0), "u1", "u0")):
        faces.append((GeomFill.Surface_s(_iso(cells[cell], body_side), _iso(plate, plate_side)),
                      "plate_walls"))
    return faces


def car_rear_shape():
    """The sewn shell and, per sewn face, its name."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_Sewing
    from OCP.gp import gp_Pnt, gp_Vec
    from OCP.TopoDS import TopoDS

    sewing = BRepBuilderAPI_Sewing(0.01)
    built = []
    for surface, name in car_rear_faces():
        face = BRepBuilderAPI_MakeFace(surface, 1e-6).Face()
        u0, u1, v0, v1 = surface.Bounds()
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        surface.D1(0.5 * (u0 + u1), 0.5 * (v0 + v1), p, du, dv)
        if du.Crossed(dv).X() > 0:  # outward is -x
            face = TopoDS.Face(face.Reversed())
        built.append((face, name))
        sewing.Add(face)
    sewing.Perform()
    return sewing.SewedShape(), [(sewing.Modified(f), name) for f, name in built]


def write_step(path: str | Path, shape, named_faces: list[tuple[object, str]],
               product: str) -> Path:
    """A STEP AP214 file of ``shape`` (mm) with each named face's name in its ADVANCED_FACE."""
    from OCP.Interface import Interface_Static
    from OCP.STEPCAFControl import STEPCAFControl_Controller, STEPCAFControl_Writer
    from OCP.STEPControl import STEPControl_AsIs
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDataStd import TDataStd_Name
    from OCP.TDocStd import TDocStd_Document
    from OCP.XCAFDoc import XCAFDoc_DocumentTool

    quiet_opencascade()
    STEPCAFControl_Controller.Init_s()
    Interface_Static.SetIVal_s("write.stepcaf.subshapes.name", 1)
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    doc = TDocStd_Document(TCollection_ExtendedString("XmlOcaf"))
    tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    label = tool.AddShape(shape, False)
    TDataStd_Name.Set_s(label, TCollection_ExtendedString(product))
    for face, name in named_faces:
        TDataStd_Name.Set_s(tool.AddSubShape(label, face), TCollection_ExtendedString(name))
    writer = STEPCAFControl_Writer()
    writer.SetNameMode(True)
    p = Path(path)
    if not writer.Transfer(doc, STEPControl_AsIs) or int(writer.Write(str(p))) != 1:
        raise OSError(f"{p}: OpenCASCADE could not write the STEP file")
    return p


def export_nominal(part: str, folder: str | Path) -> dict[str, str]:
    """``folder/<nominal>.step`` (where the part has a CAD model) and ``<nominal>.stl`` of a
    simulated part's nominal, in the part's own frame (mm)."""
    import open3d as o3d

    nominal = parts.NOMINAL_OF.get(part, part)
    if nominal not in parts.PARTS:
        raise ValueError(f"no simulated part {part!r} (known: {sorted(parts.PARTS)})")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    shapes = {"car_rear": car_rear_shape, "car_body": car_body_shape}
    if nominal in shapes:
        shape, named = shapes[nominal]()
        files["step"] = str(write_step(out / f"{nominal}.step", shape, named, nominal))
    mesh = parts.PARTS[nominal]()
    mesh.compute_vertex_normals()
    stl = out / f"{nominal}.stl"
    if not o3d.io.write_triangle_mesh(str(stl), mesh):
        raise OSError(f"{stl}: Open3D could not write the STL")
    files["stl"] = str(stl)
    return files
