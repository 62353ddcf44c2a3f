"""Triangle meshes of the simulated cell's objects, each in its own frame (mm).

- ``car_rear``: a car-body-rear-like panel of 1400 (y) x 500 (z) x 400 (x) mm: smooth double
  curvature, flanks curving back 400 mm, a feature-line crease, and a 12 mm deep licence-plate
  recess with steep walls. It faces -x (the viewer stands at negative x).
- ``car_rear_defects``: the car rear with three known form errors (:data:`CAR_REAR_DEFECTS`): a
  dent, a twist and the right flank (a flange) out of position; its nominal is ``car_rear``.
- ``car_body``: a whole body-in-white-like car, 4600 x 1800 x 1400 mm (sim/car_body.py).
- ``flat``: a 300 x 300 mm plate facing -x (VDI/VDE 2634-2 flatness artefact).
- ``dumbbell``: two 30 mm spheres, 200 mm apart on a bar (sphere-spacing artefact).
- ``smr``: a 38.1 mm (1.5") SMR whose corner-cube opening (approximated by a cone to the
  centre, 35° half-angle) faces +z of its frame.
- ``scanner_body``: the scanner housing in MCS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scancell.model.ecs import SMR_RADIUS_MM
from scancell.sim.car_body import car_body

SMR_OPENING_HALF_ANGLE_DEG = 35.0


def _mesh(vertices: np.ndarray, triangles: np.ndarray) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, float)),
                                  o3d.utility.Vector3iVector(np.asarray(triangles, np.int32)))
    m.compute_triangle_normals()
    return m


def heightfield(ys: np.ndarray, zs: np.ndarray, depth: np.ndarray) -> o3d.geometry.TriangleMesh:
    """Surface x = depth[iz, iy] over the (y, z) grid, wound so normals face -x."""
    Y, Z = np.meshgrid(ys, zs)
    verts = np.stack([depth.ravel(), Y.ravel(), Z.ravel()], axis=1)
    ny = len(ys)
    iz, iy = np.meshgrid(np.arange(len(zs) - 1), np.arange(ny - 1), indexing="ij")
    a = (iz * ny + iy).ravel()
    b, c, d = a + 1, a + ny, a + ny + 1
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return _mesh(verts, tris)


def car_rear_depth(Y: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Depth x (mm, 0 ... 400) of the car-rear surface at (y, z)."""
    half_w, depth = 700.0, 400.0
    b = 1.0 - np.clip(np.abs(Y) / half_w, 0, 1) ** 6  # flat middle, flanks curve back
    crease = -120.0
    up = np.clip((Z - crease) / 370.0, 0, None)
    c = np.where(Z > crease, 1.0 - 0.5 * up ** 1.5, 1.0 - 0.04 * ((crease - Z) / 130.0) ** 2)
    x = depth * (1.0 - b * c) + 30.0 * (Y / half_w) ** 2 * b
    plate = (np.abs(Y) < 260) & (Z > -235) & (Z < -135)
    return np.where(plate, x + 12.0, x)


#: the licence-plate recess: its walls run from these body edges (y, z) ...
PLATE_BODY_EDGES = ((-260.2, 260.2), (-235.2, -134.8))
#: ... to these edges of the recessed plate, 12 mm deeper
PLATE_FLOOR_EDGES = ((-259.8, 259.8), (-234.8, -135.2))
CAR_REAR_Y, CAR_REAR_Z = (-700.0, 700.0), (-250.0, 250.0)


@dataclass(frozen=True)
class FormDefect:
    """A known form error of ``car_rear_defects``: where it is (part frame, mm) and the signed
    deviation it makes there (mm along the nominal's outward normal; + = material outside)."""

    name: str
    at_mm: tuple[float, float, float]
    deviation_mm: float


#: dent: 0.5 mm deep (x += 0.5 exp(-r^2 / 2 sigma^2), sigma 25 mm) at y = -350, z = 100;
#: twist about the y axis: x += 0.3 mm * (y / 700) * (z / 250), +-0.3 mm at the corners;
#: flange: the right flank (y > 600) 0.6 mm further out in +y, blended in over 560 ... 600.
DENT_YZ, DENT_SIGMA_MM, DENT_DEPTH_MM = (-350.0, 100.0), 25.0, 0.5
TWIST_MM = 0.3
FLANGE_Y0, FLANGE_Y1, FLANGE_SHIFT_MM = 560.0, 600.0, 0.6


DEFECTS = ("dent", "twist", "flange")


def car_rear_defect_depth(Y: np.ndarray, Z: np.ndarray,
                          defects: tuple[str, ...] = DEFECTS) -> np.ndarray:
    """Depth x (mm) of ``car_rear_defects`` at (y, z): the nominal with the named defects."""
    x = np.zeros(np.broadcast(Y, Z).shape)
    if "dent" in defects:
        r2 = (Y - DENT_YZ[0]) ** 2 + (Z - DENT_YZ[1]) ** 2
        x = x + DENT_DEPTH_MM * np.exp(-r2 / (2 * DENT_SIGMA_MM**2))
    if "twist" in defects:
        x = x + TWIST_MM * (Y / 700.0) * (Z / 250.0)
    shift = 0.0
    if "flange" in defects:
        blend = np.clip((Y - FLANGE_Y0) / (FLANGE_Y1 - FLANGE_Y0), 0, 1)
        shift = FLANGE_SHIFT_MM * blend * blend * (3 - 2 * blend)  # smoothstep
    return car_rear_depth(Y - shift, Z) + x


def car_rear_defects_truth(defects: tuple[str, ...] = DEFECTS) -> list[FormDefect]:
    """The defects' signed deviations at telling points, from the depth functions: the dent's
    centre; the twist near two upper corners of the body; the right flank half-way up."""
    def along_normal(y: float, z: float) -> float:
        h = 0.01
        f = car_rear_depth
        fy = float(f(np.array(y + h), np.array(z)) - f(np.array(y - h), np.array(z))) / (2 * h)
        fz = float(f(np.array(y), np.array(z + h)) - f(np.array(y), np.array(z - h))) / (2 * h)
        n = np.array([-1.0, fy, fz]) / np.sqrt(1 + fy**2 + fz**2)  # outward: towards -x
        # the defect surface point over the same (y, z) line, displaced along x only; its
        # deviation along n is -dx * n_x to first order
        dx = (car_rear_defect_depth(np.array(y), np.array(z), defects)
              - car_rear_depth(np.array(y), np.array(z)))
        return float(dx * n[0])

    where = {"dent": [("dent", *DENT_YZ)], "flange": [("flange", 650.0, 0.0)],
             "twist": [(f"twist at y={y:+.0f}", y, 220.0) for y in (-450.0, 450.0)]}
    return [FormDefect(name, (float(car_rear_depth(np.array(y), np.array(z))), y, z),
                       along_normal(y, z))
            for d in defects for name, y, z in where[d]]


def _car_rear_grid(spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    ys = np.arange(CAR_REAR_Y[0], CAR_REAR_Y[1] + 1e-9, spacing_mm)
    zs = np.arange(CAR_REAR_Z[0], CAR_REAR_Z[1] + 1e-9, spacing_mm)
    # put grid lines on the licence-plate walls so they stay steep
    ys = np.unique(np.concatenate([ys, *PLATE_BODY_EDGES[:1], *PLATE_FLOOR_EDGES[:1]]))
    zs = np.unique(np.concatenate([zs, *PLATE_BODY_EDGES[1:], *PLATE_FLOOR_EDGES[1:]]))

    def off_the_walls(v: np.ndarray, body: tuple[float, float], floor: tuple[float, float]):
        inside = np.zeros(len(v), bool)
        for a, b in zip(body, floor, strict=True):  # nothing between a wall's two edges
            inside |= (v > min(a, b) + 1e-9) & (v < max(a, b) - 1e-9)
        return v[~inside]

    return (off_the_walls(ys, PLATE_BODY_EDGES[0], PLATE_FLOOR_EDGES[0]),
            off_the_walls(zs, PLATE_BODY_EDGES[1], PLATE_FLOOR_EDGES[1]))


def car_rear(spacing_mm: float = 2.0) -> o3d.geometry.TriangleMesh:
    """The car rear at ``spacing_mm``: 2 mm keeps the facets within 0.013 mm of the smooth
    surface its CAD nominal (sim/cad.py) describes, on the flanks' tightest curvature."""
    ys, zs = _car_rear_grid(spacing_mm)
    Y, Z = np.meshgrid(ys, zs)
    return heightfield(ys, zs, car_rear_depth(Y, Z))


def car_rear_defects(spacing_mm: float = 2.0, defects: tuple[str, ...] = DEFECTS
                     ) -> o3d.geometry.TriangleMesh:
    ys, zs = _car_rear_grid(spacing_mm)
    Y, Z = np.meshgrid(ys, zs)
    return heightfield(ys, zs, car_rear_defect_depth(Y, Z, defects))


def flat(size_mm: float = 300.0, thickness_mm: float = 20.0) -> o3d.geometry.TriangleMesh:
    """Front face at x = 0 facing -x, centred on the origin."""
    m = o3d.geometry.TriangleMesh.create_box(thickness_mm, size_mm, size_mm)
    m.translate([0.0, -size_mm / 2, -size_mm / 2])
    m.compute_triangle_normals()
    return m


def sphere(radius_mm: float, resolution: int = 96) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_sphere(radius_mm, resolution)
    m.compute_triangle_normals()
    return m


def dumbbell(radius_mm: float = 15.0, spacing_mm: float = 200.0) -> o3d.geometry.TriangleMesh:
    """Two spheres on the y axis at +-spacing/2 and a thin bar behind them (+x)."""
    a = sphere(radius_mm).translate([0, -spacing_mm / 2, 0])
    b = sphere(radius_mm).translate([0, spacing_mm / 2, 0])
    bar = o3d.geometry.TriangleMesh.create_cylinder(3.0, spacing_mm - 2 * radius_mm, 24)
    bar.rotate(o3d.geometry.get_rotation_matrix_from_xyz([np.pi / 2, 0, 0]), center=[0, 0, 0])
    bar.translate([radius_mm + 5.0, 0, 0])
    m = a + b + bar
    m.compute_triangle_normals()
    return m


def smr(radius_mm: float = SMR_RADIUS_MM,
        opening_half_angle_deg: float = SMR_OPENING_HALF_ANGLE_DEG,
        resolution: int = 96) -> o3d.geometry.TriangleMesh:
    """A sphere with its corner-cube opening towards +z: the cap is replaced by a cone to the
    centre, so a scanner looking into the opening sees points inside the ball."""
    m = sphere(radius_mm, resolution)
    v = np.asarray(m.vertices)
    t = np.asarray(m.triangles)
    cos_open = np.cos(np.radians(opening_half_angle_deg))
    centroid_dir = v[t].mean(axis=1)
    centroid_dir /= np.linalg.norm(centroid_dir, axis=1, keepdims=True)
    keep = centroid_dir[:, 2] < cos_open
    n_rim = resolution * 2
    ang = np.linspace(0, 2 * np.pi, n_rim, endpoint=False)
    s = np.sin(np.radians(opening_half_angle_deg))
    rim = radius_mm * np.stack([s * np.cos(ang), s * np.sin(ang), np.full_like(ang, cos_open)], 1)
    base = len(v)
    verts = np.concatenate([v, rim, [[0.0, 0.0, 0.0]]])
    apex = base + n_rim
    i = np.arange(n_rim)
    cone = np.stack([base + i, base + (i + 1) % n_rim, np.full(n_rim, apex)], 1)
    return _mesh(verts, np.concatenate([t[keep], cone]))


def ball_stand(height_mm: float = 150.0) -> o3d.geometry.TriangleMesh:
    """A post under an SMR whose centre is the frame origin (the post hangs down -z)."""
    post = o3d.geometry.TriangleMesh.create_cylinder(6.0, height_mm, 24)
    post.translate([0, 0, -SMR_RADIUS_MM - height_mm / 2])
    post.compute_triangle_normals()
    return post


def scanner_body() -> o3d.geometry.TriangleMesh:
    """Housing behind the lenses, in MCS (left camera at the origin, right camera ~ +293 mm x)."""
    m = o3d.geometry.TriangleMesh.create_box(420.0, 110.0, 150.0)
    m.translate([-60.0, -55.0, -165.0])
    m.compute_triangle_normals()
    return m


#: SMR nests on the housing (issue 19): a triangle of three 1.5" SMRs, 70 mm from its centre,
#: 25 mm out from each of the back, left and right faces; the back ones open backwards, the side
#: ones half-way between the face normal and backwards (45 deg), so that the tracker sees a side
#: face and the back at once over a band of directions: the hand-eye job's J6 turns calibrate
#: the side faces from the poses the rear SMR gives. Three on one face fix the pose.
#: name -> (centre in mcs, opening direction in mcs)
HOUSING_SMR_CLUSTER = {
    "back1": ((210.0, -36.0, -190.0), (0.0, 0.0, -1.0)),
    "back2": ((88.8, -34.0, -190.0), (0.0, 0.0, -1.0)),
    "back3": ((151.2, 70.0, -190.0), (0.0, 0.0, -1.0)),
    "left1": ((-85.0, 59.4, -127.1), (-0.7071, 0.0, -0.7071)),
    "left2": ((-85.0, -61.8, -122.9), (-0.7071, 0.0, -0.7071)),
    "left3": ((-85.0, 2.5, -20.0), (-0.7071, 0.0, -0.7071)),
    "right1": ((385.0, -59.4, -52.9), (0.7071, 0.0, -0.7071)),
    "right2": ((385.0, -2.5, -160.0), (0.7071, 0.0, -0.7071)),
    "right3": ((385.0, 61.8, -57.1), (0.7071, 0.0, -0.7071)),
}


#: VDI/VDE 2634-2 artefacts as the simulated cell's calibration certificates state them (mm);
#: deploy/cells/sim.toml [acceptance] repeats these values
ACCEPTANCE_SPHERE_DIAMETER_MM = 50.0
BALLBAR_LENGTH_MM, BALLBAR_SPHERE_DIAMETER_MM = 200.0, 30.0
PLANE_SIZE_MM = (200.0, 50.0)
#: VDI/VDE 2634-3: a ball bar longer than one view, measured from two robot stations
BALLBAR3_LENGTH_MM, BALLBAR3_SPHERE_DIAMETER_MM = 800.0, 30.0


def plane_artefact(size_mm: tuple[float, float] = PLANE_SIZE_MM, thickness_mm: float = 15.0
                   ) -> o3d.geometry.TriangleMesh:
    """A flatness standard: its front face at x = 0 facing -x, long along y, centred."""
    m = o3d.geometry.TriangleMesh.create_box(thickness_mm, size_mm[0], size_mm[1])
    m.translate([0.0, -size_mm[0] / 2, -size_mm[1] / 2])
    m.compute_triangle_normals()
    return m


#: artefact -> its mesh in its own frame: front towards -x; a ball bar's spheres along y
ARTEFACTS = {
    "sphere": lambda: sphere(ACCEPTANCE_SPHERE_DIAMETER_MM / 2, 192),
    "ballbar": lambda: dumbbell(BALLBAR_SPHERE_DIAMETER_MM / 2, BALLBAR_LENGTH_MM),
    "plane": plane_artefact,
    "ballbar3": lambda: dumbbell(BALLBAR3_SPHERE_DIAMETER_MM / 2, BALLBAR3_LENGTH_MM),
}


PARTS = {"car_rear": car_rear, "car_rear_defects": car_rear_defects, "flat": flat,
         "dumbbell": dumbbell, "car_body": car_body}
#: the nominal (CAD) of each part that has one other than itself
NOMINAL_OF = {"car_rear_defects": "car_rear"}

#: paint regions (indices into OpticsProfile.paint_table): 0 the part's one paint
REGION_DEFAULT, REGION_BODY, REGION_BUMPER, REGION_PLATE = 0, 1, 2, 3


def paint_regions(part: str, mesh: o3d.geometry.TriangleMesh) -> np.ndarray | None:
    """Paint region of each triangle of a part's mesh, or None for a one-paint part. The car
    rear: the body above the feature-line crease, the bumper below it, the licence plate."""
    if part not in ("car_rear", "car_rear_defects"):
        return None
    centre = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)
    y, z = centre[:, 1], centre[:, 2]
    regions = np.where(z > -120.0, REGION_BODY, REGION_BUMPER).astype(np.int8)
    regions[(np.abs(y) < 260) & (z > -235) & (z < -135)] = REGION_PLATE
    return regions
