"""Single-origin ray casting against MuJoCo primitive geoms (numba), the camera's ``"numba"`` engine.

:func:`mujoco.mj_multiRay` tests every ray against every geom (about 20 ms for the
283x160 image of the vine scene with its ~75 geoms, too slow for 30 Hz at 3x real
time). :func:`cast_rays` gives the same distances and geom ids (``mj_multiRay`` is its
reference: tests/sim/test_sim_camera.py holds the two to 1e-9 m on lab frames) in
~0.5-0.8 ms by testing each geom only against the pixels inside its projected bounding
sphere (and, for ellipsoids, capsules and cylinders, its quadric's footprint on each
row), with the same filters as ``mj_multiRay`` (transparent geoms, ``bodyexclude``,
geoms farther than ``cutoff``). Planes, spheres, ellipsoids and capsules are intersected
a row span at a time in branch-free loops that the compiler vectorises; cylinders and
boxes a pixel at a time. A model with other geom types (meshes, height fields, SDFs)
must use ``mj_multiRay``.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from numba import njit

__all__ = ["SUPPORTED_GEOM_TYPES", "VISUAL_GROUP", "visual_only_geoms", "supports_model", "cast_rays"]

#: MuJoCo's convention (menagerie; ``harvest_qp.robot.meshes``): visual-only geoms are in group 2.
VISUAL_GROUP = 2

_PLANE = int(mujoco.mjtGeom.mjGEOM_PLANE)
_SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_ELLIPSOID = int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)
_CYLINDER = int(mujoco.mjtGeom.mjGEOM_CYLINDER)
_BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
SUPPORTED_GEOM_TYPES = frozenset((_PLANE, _SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX))


def visual_only_geoms(model: mujoco.MjModel) -> np.ndarray:
    """(ngeom,) bool: geoms for drawing only (group 2, no contact: ``contype = conaffinity = 0``).

    The depth camera never sees them: the lab's robot is its collision capsules (the UR5e
    meshes drawn over them are decoration), so a depth pixel and its label always belong
    to a geom the physics knows.
    """
    return (
        (np.asarray(model.geom_group) == VISUAL_GROUP)
        & (np.asarray(model.geom_contype) == 0)
        & (np.asarray(model.geom_conaffinity) == 0)
    )


def supports_model(model: mujoco.MjModel) -> bool:
    """True when every geom of ``model`` the camera can see is a primitive this kernel handles."""
    seen = ~visual_only_geoms(model)
    return all(int(t) in SUPPORTED_GEOM_TYPES for t in np.asarray(model.geom_type)[seen])


@njit(cache=True, inline="always")
def _keep(best, t):
    if t >= 0.0 and (best < 0.0 or t < best):
        return t
    return best


@njit(cache=True, inline="always", error_model="numpy")
def _root(a, b, c):
    """Smallest non-negative root of a t^2 + 2 b t + c = 0, or -1 (branch-free: both roots
    computed, the kept one selected)."""
    det = b * b - a * c
    s = math.sqrt(det) if det >= 0.0 else 0.0
    t0 = (-b - s) / a
    t1 = (-b + s) / a
    t = t0 if t0 >= 0.0 else (t1 if t1 >= 0.0 else -1.0)
    return t if (det >= 0.0 and a >= 1e-15) else -1.0


@njit(cache=True, error_model="numpy")
def _span_distances(
    gt, rays_x, rays_y, rays_z, base, ua, ub, r00, r01, r02, r10, r11, r12, r20, r21, r22, ox, oy, oz, s0, s1, s2,
    tbuf,
):  # fmt: skip
    """Distances (-1: miss) of the rays base+ua .. base+ub to a plane (0), a sphere (2), an ellipsoid (4)
    or a capsule (3) into ``tbuf[ua..ub]``, branch-free so that it vectorises (``_root``: the
    smallest non-negative root of a t^2 + 2 b t + c). ``error_model="numpy"`` leaves out the
    zero-division checks (no division here is by zero where its result is kept).
    """
    n = ub + 1 - ua
    ex_ = rays_x[base + ua : base + ub + 1]
    ey_ = rays_y[base + ua : base + ub + 1]
    ez_ = rays_z[base + ua : base + ub + 1]
    out = tbuf[ua : ub + 1]
    if gt == 0:
        # Plane: front face only, within the rectangle (size 0 = infinite); the division is
        # done for every pixel, its result kept only where the scalar code divides.
        for j in range(n):
            ex, ey, ez = ex_[j], ey_[j], ez_[j]
            dx = r00 * ex + r10 * ey + r20 * ez
            dy = r01 * ex + r11 * ey + r21 * ez
            dz = r02 * ex + r12 * ey + r22 * ez
            t = -oz / dz
            px = ox + t * dx
            py = oy + t * dy
            inside = (s0 <= 0.0 or abs(px) <= s0) and (s1 <= 0.0 or abs(py) <= s1)
            out[j] = t if (not dz > -1e-15 and t >= 0.0 and inside) else -1.0
    elif gt == 2 or gt == 4:
        # Sphere or ellipsoid (semi-axes a, b, c; a sphere's all its radius): scaled to the
        # unit sphere (t is unchanged).
        ia = 1.0 / s0
        ib = ia if gt == 2 else 1.0 / s1
        ic = ia if gt == 2 else 1.0 / s2
        px, py, pz = ox * ia, oy * ib, oz * ic
        c = px * px + py * py + pz * pz - 1.0
        for j in range(n):
            ex, ey, ez = ex_[j], ey_[j], ez_[j]
            dx = (r00 * ex + r10 * ey + r20 * ez) * ia
            dy = (r01 * ex + r11 * ey + r21 * ez) * ib
            dz = (r02 * ex + r12 * ey + r22 * ez) * ic
            out[j] = _root(dx * dx + dy * dy + dz * dz, px * dx + py * dy + pz * dz, c)
    else:
        # Capsule: the cylinder's side within its half-length, and the two end spheres.
        c_side = ox * ox + oy * oy - s0 * s0
        zl = oz - s1
        zh = oz + s1
        c_low = ox * ox + oy * oy + zl * zl - s0 * s0
        c_high = ox * ox + oy * oy + zh * zh - s0 * s0
        for j in range(n):
            ex, ey, ez = ex_[j], ey_[j], ez_[j]
            dx = r00 * ex + r10 * ey + r20 * ez
            dy = r01 * ex + r11 * ey + r21 * ez
            dz = r02 * ex + r12 * ey + r22 * ez
            t = _root(dx * dx + dy * dy, ox * dx + oy * dy, c_side)
            t = t if (t >= 0.0 and abs(oz + t * dz) <= s1) else -1.0
            a = dx * dx + dy * dy + dz * dz
            t2 = _root(a, ox * dx + oy * dy + zl * dz, c_low)
            t = t2 if (t2 >= 0.0 and (t < 0.0 or t2 < t)) else t
            t3 = _root(a, ox * dx + oy * dy + zh * dz, c_high)
            out[j] = t3 if (t3 >= 0.0 and (t < 0.0 or t3 < t)) else t


@njit(cache=True, error_model="numpy")
def _merge_span(dist, geomid, tbuf, row, ua, ub, bound, cutoff, g):
    """The nearest-hit merge of a span's distances ``tbuf[ua..ub]`` into ``dist`` / ``geomid`` at
    ``row + ua .. row + ub``, branch-free so that it vectorises: a pixel already hit closer than
    ``bound`` keeps its hit, otherwise geom ``g`` takes it when its distance is in [0, cutoff]
    and nearer (ties to the lower id). Every pixel is stored, with its old values where ``g``
    does not take it."""
    n = ub + 1 - ua
    d = dist[row + ua : row + ub + 1]
    ids = geomid[row + ua : row + ub + 1]
    ts = tbuf[ua : ub + 1]
    gid = np.int32(g)
    for j in range(n):
        best = d[j]
        t = ts[j]
        old = ids[j]
        take = not (best >= 0.0 and best < bound) and (
            t >= 0.0 and t <= cutoff and (best < 0.0 or t < best or (t == best and gid < old))
        )
        d[j] = t if take else best
        ids[j] = gid if take else old


@njit(cache=True, error_model="numpy")
def _cylinder_or_box(gtype, size, ox, oy, oz, dx, dy, dz):
    """Distance along the ray to a cylinder (5) or a box (6) in its local frame (ray origin o,
    direction d), or -1."""
    if gtype == 5:  # cylinder: side and two end disks
        r, h = size[0], size[1]
        best = -1.0
        t = _root(dx * dx + dy * dy, ox * dx + oy * dy, ox * ox + oy * oy - r * r)
        if t >= 0.0 and abs(oz + t * dz) <= h:
            best = t
        if abs(dz) > 1e-15:
            for side in (-1.0, 1.0):
                t = (side * h - oz) / dz
                if t >= 0.0:
                    px = ox + t * dx
                    py = oy + t * dy
                    if px * px + py * py <= r * r:
                        best = _keep(best, t)
        return best
    if gtype == 6:  # box: slabs
        tmin = -1e300
        tmax = 1e300
        o = (ox, oy, oz)
        d = (dx, dy, dz)
        for i in range(3):
            if abs(d[i]) < 1e-15:
                if abs(o[i]) > size[i]:
                    return -1.0
            else:
                t1 = (-size[i] - o[i]) / d[i]
                t2 = (size[i] - o[i]) / d[i]
                if t1 > t2:
                    t1, t2 = t2, t1
                tmin = max(tmin, t1)
                tmax = min(tmax, t2)
        if tmax < tmin or tmax < 0.0:
            return -1.0
        return tmin if tmin >= 0.0 else tmax
    return -1.0


@njit(cache=True)
def _sphere_rect(c0, c1, c2, r, focal, width, height, tan_h, tan_v, rect):
    """Grow ``rect`` (u0, u1, v0, v1) by the pixels a sphere can cover; returns False if none.

    A sphere outside one of the frustum's side planes covers nothing; one reaching behind
    the image plane inside the frustum may cover any pixel (the whole image).
    """
    # Side planes through the optical centre, inward unit normals.
    nh = math.sqrt(1.0 + tan_h * tan_h)
    nv = math.sqrt(1.0 + tan_v * tan_v)
    if (c0 + tan_h * c2) / nh < -r or (-c0 + tan_h * c2) / nh < -r:
        return False
    if (c1 + tan_v * c2) / nv < -r or (-c1 + tan_v * c2) / nv < -r:
        return False
    if c2 + r <= 0.0:
        return False
    zmin = c2 - r
    if zmin <= 1e-6:
        rect[0] = 0
        rect[1] = width - 1
        rect[2] = 0
        rect[3] = height - 1
        return True
    zmax = c2 + r
    xa, xb = c0 - r, c0 + r
    ya, yb = c1 - r, c1 + r
    # Bounds of x/z and y/z over the box around the sphere.
    lx = xa / zmax if xa >= 0.0 else xa / zmin
    hx = xb / zmin if xb >= 0.0 else xb / zmax
    ly = ya / zmax if ya >= 0.0 else ya / zmin
    hy = yb / zmin if yb >= 0.0 else yb / zmax
    u0 = max(0, int(math.floor(width / 2.0 + focal * lx - 0.5)))
    u1 = min(width - 1, int(math.ceil(width / 2.0 + focal * hx - 0.5)))
    v0 = max(0, int(math.floor(height / 2.0 + focal * ly - 0.5)))
    v1 = min(height - 1, int(math.ceil(height / 2.0 + focal * hy - 0.5)))
    if u0 > u1 or v0 > v1:
        return False
    rect[0] = min(rect[0], u0)
    rect[1] = max(rect[1], u1)
    rect[2] = min(rect[2], v0)
    rect[3] = max(rect[3], v1)
    return True


@njit(cache=True)
def _cone_row_span(a0, a1, a2, k, y, focal, width):
    """Pixel columns (u0, u1) of image row ``y`` (= (v + 0.5 - h/2) / f) whose rays lie in a cone.

    The cone holds the unit rays e with a.e >= k (``a`` a unit axis, 0 <= k <= 1): the rays
    that can meet a sphere of radius r at distance d along ``a`` (k = sqrt(1 - r^2/d^2)),
    or the front face of a plane with inward normal ``a`` within a range R of a camera at
    height z above it (k = z / R). A cone with k >= 0 is convex, so on the row's line of
    unnormalised rays (x, y, 1) it is one interval of x, found from
    a0 x + b >= k sqrt(x^2 + y^2 + 1) with b = a1 y + a2. The span is padded by a pixel on
    each side (each pixel in it is still tested exactly); u0 > u1 when it is empty.
    """
    a = a0
    b = a1 * y + a2
    lo = -1e300
    hi = 1e300
    # Half-line a x + b >= 0 (the ray points into the cone's half-space).
    if a > 1e-15:
        lo = -b / a
    elif a < -1e-15:
        hi = -b / a
    elif b < 0.0:
        return 0, -1
    if k > 0.0:
        s2 = y * y + 1.0
        qa = a * a - k * k
        qb = a * b
        qc = b * b - k * k * s2
        if abs(qa) > 1e-12:
            disc = qb * qb - qa * qc
            if qa > 0.0:
                if disc > 0.0:
                    sq = math.sqrt(disc)
                    r1 = (-qb - sq) / qa
                    r2 = (-qb + sq) / qa
                    # Outside (r1, r2), within the half-line: the hull of both pieces (conservative).
                    left = lo <= r1
                    right = hi >= r2
                    if left and not right:
                        hi = min(hi, r1)
                    elif right and not left:
                        lo = max(lo, r2)
                    elif not left and not right:
                        return 0, -1
            else:
                if disc < 0.0:
                    return 0, -1
                sq = math.sqrt(disc)
                r1 = (-qb + sq) / qa
                r2 = (-qb - sq) / qa
                lo = max(lo, min(r1, r2))
                hi = min(hi, max(r1, r2))
    if lo > hi:
        return 0, -1
    half = width / 2.0 - 0.5
    ul = focal * lo + half if lo > -1e299 else -1.0
    uh = focal * hi + half if hi < 1e299 else width + 1.0
    if not (ul == ul) or not (uh == uh):  # NaN: be safe, the whole row
        return 0, width - 1
    u0 = int(min(max(0.0, math.floor(max(ul, -2.0)) - 1.0), float(width)))
    u1 = int(max(min(width - 1.0, math.ceil(min(uh, width + 1.0)) + 1.0), -1.0))
    return u0, u1


@njit(cache=True)
def _sphere_row_span(c0, c1, c2, r, y, focal, width):
    """:func:`_cone_row_span` of the rays that can meet the sphere (c, r) (camera frame)."""
    d2 = c0 * c0 + c1 * c1 + c2 * c2
    if d2 <= r * r:
        return 0, width - 1  # the camera is inside: any ray
    d = math.sqrt(d2)
    return _cone_row_span(c0 / d, c1 / d, c2 / d, math.sqrt(1.0 - r * r / d2), y, focal, width)


@njit(cache=True)
def _quadric_row_span(w0, w1, w2, o0, o1, o2, a0, a1, a2, rg, y, focal, width, pad):
    """Pixel columns (u0, u1) of image row ``y`` whose rays' lines can meet a quadric; (0, -1): none.

    The quadric is sum_i w_i x_i^2 <= 1 in a geom's frame (an ellipsoid, or with w_2 = 0 the
    infinite cylinder around a capsule or cylinder), seen from the ray origin ``o`` in that
    frame; ``a = (sum_i w_i o_i rg[0, i], sum_i w_i rg[0, i]^2, sum_i w_i o_i^2 - 1)`` are the
    row-independent sums. The ray through (x, y, 1) in the camera frame has the direction
    d = x rg[0] + y rg[1] + rg[2] in the geom frame, and its line meets the quadric where
    (sum w o d)^2 - (sum w d^2)(sum w o^2 - 1) >= 0: a quadratic A x^2 + 2 B x + C >= 0 in x,
    one interval when A < 0 (scaling d does not change its sign, so the unit rays the
    kernel casts hit the same set). The interval is padded by ``pad`` pixels on each side,
    far beyond its round-off, so every pixel outside it misses the geom in the kernel's own
    arithmetic too. Returns the whole row (no restriction) when the origin is inside or
    near the quadric or A is not clearly negative (the set is not one bounded interval).
    """
    p0, q0, c = a0, a1, a2
    if not c > 1e-6:
        return 0, width - 1
    k0 = y * rg[1, 0] + rg[2, 0]
    k1 = y * rg[1, 1] + rg[2, 1]
    k2 = y * rg[1, 2] + rg[2, 2]
    pk = w0 * o0 * k0 + w1 * o1 * k1 + w2 * o2 * k2
    rk = w0 * rg[0, 0] * k0 + w1 * rg[0, 1] * k1 + w2 * rg[0, 2] * k2
    kk = w0 * k0 * k0 + w1 * k1 * k1 + w2 * k2 * k2
    qa = p0 * p0 - c * q0
    qb = p0 * pk - c * rk
    qc = pk * pk - c * kk
    if not qa < -1e-9 * (p0 * p0 + c * q0):
        return 0, width - 1
    disc = qb * qb - qa * qc
    scale = qb * qb + abs(qa * qc)
    if disc < -1e-9 * scale:
        return 0, -1  # the row's plane misses the quadric
    sq = math.sqrt(max(disc, 0.0))
    lo = (-qb + sq) / qa  # qa < 0: the smaller root
    hi = (-qb - sq) / qa
    half = width / 2.0 - 0.5
    ul = focal * lo + half
    uh = focal * hi + half
    if not (abs(ul) < 1e9 and abs(uh) < 1e9):
        return 0, width - 1
    u0 = max(0, int(math.floor(ul)) - pad)
    u1 = min(width - 1, int(math.ceil(uh)) + pad)
    return u0, u1


@njit(cache=True)
def cast_rays(
    height,
    width,
    focal,
    origin,  # (3,) camera position (world)
    rotation,  # (3, 3) camera rotation (world from camera)
    geom_type,  # (ngeom,) int
    geom_size,  # (ngeom, 3)
    geom_xpos,  # (ngeom, 3)
    geom_xmat,  # (ngeom, 9)
    geom_rbound,  # (ngeom,) bounding-sphere radius; 0 = unbounded (planes)
    geom_mask,  # (ngeom,) bool: geoms that can be hit
    cutoff,  # ignore geoms farther than this [m]
    geomid,  # out (h*w,) int32
    dist,  # out (h*w,) float64 (-1: no hit)
    rays_x,  # (h*w,) x of the unit pixel rays in the camera frame, row-major
    rays_y,  # (h*w,) their y
    rays_z,  # (h*w,) their z
):
    """For every pixel ray, the nearest geom hit (id, distance) as ``mj_multiRay`` returns them.

    Geoms are culled to the pixels their bounding spheres can cover (planes: the rows'
    spans whose rays reach them within ``cutoff``), then drawn nearest bound first: a
    pixel already hit closer than a geom's nearest possible point skips that geom, so
    occluded geoms cost a comparison per pixel. Ties in distance go to the lowest geom id,
    as when the geoms are tested in id order.
    """
    n = rays_x.shape[0]
    for i in range(n):
        geomid[i] = -1
        dist[i] = -1.0
    order, rects, rgs, locs, near, cens, nsub, rsub, quad, qw, qsum = _setup(
        height, width, focal, origin, rotation, geom_type, geom_size, geom_xpos, geom_xmat, geom_rbound, geom_mask,
        cutoff,
    )  # fmt: skip
    _draw(
        0, height - 1, 0, order, rects, rgs, locs, near, cens, nsub, rsub, quad, qw, qsum, height, width, focal,
        geom_type, geom_size, cutoff, rays_x, rays_y, rays_z, dist, geomid, np.empty(width),
    )  # fmt: skip


@njit(cache=True)
def _setup(
    height, width, focal, origin, rotation, geom_type, geom_size, geom_xpos, geom_xmat, geom_rbound, geom_mask, cutoff,
):  # fmt: skip
    """Per geom in the camera frame: pixel rectangle, rotation, ray origin, nearest possible hit,
    row-span bounds (axis spheres, quadric); and the geoms that can be seen, nearest bound first."""
    # Half-extents of the frustum slightly enlarged: pixel rays reach to half a pixel in.
    tan_h = (width / 2.0 + 1.0) / focal
    tan_v = (height / 2.0 + 1.0) / focal
    ng = geom_type.shape[0]
    rect = np.empty(4, np.int64)
    rects = np.empty((ng, 4), np.int64)
    rgs = np.empty((ng, 3, 3))
    locs = np.empty((ng, 3))  # ray origin in the geom frame
    near = np.empty(ng)  # lower bound of any hit distance
    cens = np.empty((ng, 3))  # centre in the camera frame
    nsub = np.zeros(ng, np.int64)  # bounding spheres per row span (0: whole rows)
    rsub = np.zeros(ng)  # their radius
    # Quadric bounding the geom's footprint per row (see _quadric_row_span): weights and sums.
    quad = np.zeros(ng, np.bool_)
    qw = np.zeros((ng, 3))
    qsum = np.zeros((ng, 3))
    todo = np.empty(ng, np.int64)
    count = 0
    for g in range(ng):
        if not geom_mask[g]:
            continue
        # Geom centre and rotation in the camera frame.
        px = geom_xpos[g, 0] - origin[0]
        py = geom_xpos[g, 1] - origin[1]
        pz = geom_xpos[g, 2] - origin[2]
        c0 = rotation[0, 0] * px + rotation[1, 0] * py + rotation[2, 0] * pz
        c1 = rotation[0, 1] * px + rotation[1, 1] * py + rotation[2, 1] * pz
        c2 = rotation[0, 2] * px + rotation[1, 2] * py + rotation[2, 2] * pz
        # Rg_c = R^T Rg (3x3), row-major.
        rg = rgs[g]
        for a in range(3):
            for b in range(3):
                rg[a, b] = (
                    rotation[0, a] * geom_xmat[g, 0 * 3 + b]
                    + rotation[1, a] * geom_xmat[g, 1 * 3 + b]
                    + rotation[2, a] * geom_xmat[g, 2 * 3 + b]
                )
        # Ray origin in the geom frame: -Rg_c^T c.
        ox = -(rg[0, 0] * c0 + rg[1, 0] * c1 + rg[2, 0] * c2)
        oy = -(rg[0, 1] * c0 + rg[1, 1] * c1 + rg[2, 1] * c2)
        oz = -(rg[0, 2] * c0 + rg[1, 2] * c1 + rg[2, 2] * c2)
        locs[g, 0] = ox
        locs[g, 1] = oy
        locs[g, 2] = oz
        cens[g, 0] = c0
        cens[g, 1] = c1
        cens[g, 2] = c2
        r = geom_rbound[g]
        gt = geom_type[g]
        if gt != 0 and r > 0.0:
            centre_distance = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            if centre_distance - r > cutoff:
                continue
            rect[0] = width
            rect[1] = -1
            rect[2] = height
            rect[3] = -1
            half = geom_size[g, 1]
            radius = geom_size[g, 0]
            if (gt == 3 or gt == 5) and half > radius:
                # Long capsule or cylinder: bound it by spheres along its axis, so a geom
                # passing beside or behind the camera does not cover the whole image.
                k = min(16, int(math.ceil(half / radius)))
                sub = radius + half / k
                seen = False
                for j in range(k):
                    s = half * ((2.0 * j + 1.0) / k - 1.0)
                    if _sphere_rect(
                        c0 + rg[0, 2] * s,
                        c1 + rg[1, 2] * s,
                        c2 + rg[2, 2] * s,
                        sub,
                        focal,
                        width,
                        height,
                        tan_h,
                        tan_v,
                        rect,
                    ):
                        seen = True
                if not seen:
                    continue
                nsub[g] = k
                rsub[g] = sub
            elif not _sphere_rect(c0, c1, c2, r, focal, width, height, tan_h, tan_v, rect):
                continue
            else:
                nsub[g] = 1
                rsub[g] = r
            rects[g, 0] = rect[0]
            rects[g, 1] = rect[1]
            rects[g, 2] = rect[2]
            rects[g, 3] = rect[3]
            near[g] = max(0.0, centre_distance - r)
            if gt == 4 or gt == 3 or gt == 5:
                # Ellipsoid: itself; capsule and cylinder: the infinite cylinder around them.
                if gt == 4:
                    w0 = 1.0 / (geom_size[g, 0] * geom_size[g, 0])
                    w1 = 1.0 / (geom_size[g, 1] * geom_size[g, 1])
                    w2 = 1.0 / (geom_size[g, 2] * geom_size[g, 2])
                else:
                    w0 = 1.0 / (radius * radius)
                    w1 = w0
                    w2 = 0.0
                quad[g] = True
                qw[g, 0] = w0
                qw[g, 1] = w1
                qw[g, 2] = w2
                qsum[g, 0] = w0 * ox * rg[0, 0] + w1 * oy * rg[0, 1] + w2 * oz * rg[0, 2]
                qsum[g, 1] = w0 * rg[0, 0] * rg[0, 0] + w1 * rg[0, 1] * rg[0, 1] + w2 * rg[0, 2] * rg[0, 2]
                qsum[g, 2] = w0 * ox * ox + w1 * oy * oy + w2 * oz * oz - 1.0
        elif gt == 0:
            # Plane: only its front face is hit, from a camera above it and within range.
            if oz < 0.0 or oz > cutoff:
                continue
            rects[g, 0] = 0
            rects[g, 1] = width - 1
            rects[g, 2] = 0
            rects[g, 3] = height - 1
            near[g] = oz
        else:
            rects[g, 0] = 0
            rects[g, 1] = width - 1
            rects[g, 2] = 0
            rects[g, 3] = height - 1
            near[g] = 0.0
        todo[count] = g
        count += 1
    order = todo[:count][np.argsort(near[todo[:count]], kind="mergesort")]
    return order, rects, rgs, locs, near, cens, nsub, rsub, quad, qw, qsum


#: Geoms whose pixel rectangle has at most this many pixels are first checked for being hidden
#: whole (:func:`_occluded`); on larger ones the check could cost more than it saves.
_SMALL_RECT = 1024


@njit(cache=True)
def _occluded(dist, va, vb, u0, u1, row0, width, bound):
    """True when every pixel of rows va..vb, columns u0..u1 is already hit closer than ``bound``
    (then a geom whose hits are all at least ``bound`` away changes none of them)."""
    for v in range(va, vb + 1):
        row = (v - row0) * width
        for u in range(u0, u1 + 1):
            d = dist[row + u]
            if not (d >= 0.0 and d < bound):
                return False
    return True


@njit(cache=True)
def _draw(
    v_lo, v_hi, row0, order, rects, rgs, locs, near, cens, nsub, rsub, quad, qw, qsum, height, width, focal,
    geom_type, geom_size, cutoff, rays_x, rays_y, rays_z, dist, geomid, tbuf,
):  # fmt: skip
    """Draw the geoms of ``order`` into image rows v_lo..v_hi: the buffers (rays, ``dist``,
    ``geomid``) hold rows from ``row0`` on, pixel (v, u) at (v - row0) * width + u."""
    for g in order:
        if rects[g, 3] < v_lo or rects[g, 2] > v_hi:
            continue
        rg = rgs[g]
        ox = locs[g, 0]
        oy = locs[g, 1]
        oz = locs[g, 2]
        gt = geom_type[g]
        size = geom_size[g]
        bound = near[g]
        u0, u1, v0, v1 = rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3]
        va, vb = max(v0, v_lo), min(v1, v_hi)
        if (u1 - u0 + 1) * (vb - va + 1) <= _SMALL_RECT and _occluded(dist, va, vb, u0, u1, row0, width, bound):
            continue  # every pixel it could cover is already hit closer than it can be: nothing to draw
        plane = gt == 0
        n0, n1, n2 = rg[0, 2], rg[1, 2], rg[2, 2]
        k_plane = oz / cutoff if plane else 0.0
        m = nsub[g]
        rs = rsub[g]
        half = geom_size[g, 1]
        c0, c1, c2 = cens[g, 0], cens[g, 1], cens[g, 2]
        # Loop invariants in scalars (the compiler cannot tell that dist and geomid do not alias them).
        r00, r01, r02 = rg[0, 0], rg[0, 1], rg[0, 2]
        r10, r11, r12 = rg[1, 0], rg[1, 1], rg[1, 2]
        r20, r21, r22 = rg[2, 0], rg[2, 1], rg[2, 2]
        s0, s1, s2 = size[0], size[1], size[2]
        use_quad = quad[g]
        w0, w1, w2 = qw[g, 0], qw[g, 1], qw[g, 2]
        a0, a1, a2 = qsum[g, 0], qsum[g, 1], qsum[g, 2]
        for v in range(max(v0, v_lo), min(v1, v_hi) + 1):
            ua, ub = u0, u1
            y = (v + 0.5 - height / 2.0) / focal
            restricted = False
            if use_quad:
                # The geom's quadric (see _quadric_row_span); for a long capsule or cylinder its
                # infinite cylinder makes the axis spheres' spans below unnecessary, the
                # geom's rectangle bounding it along the axis.
                ua, ub = _quadric_row_span(w0, w1, w2, ox, oy, oz, a0, a1, a2, rg, y, focal, width, 2)
                restricted = ua > 0 or ub < width - 1
                if ua > ub:
                    continue
            if plane:
                ua, ub = _cone_row_span(-n0, -n1, -n2, k_plane, y, focal, width)
            elif m == 1:
                sa, sb = _sphere_row_span(c0, c1, c2, rs, y, focal, width)
                ua = max(ua, sa)
                ub = min(ub, sb)
            elif m > 1 and not restricted:
                # Long capsule or cylinder: the hull of its axis spheres' spans (its footprint
                # on a row is one interval: the geom is convex).
                ua, ub = width, -1
                for j in range(m):
                    s = half * ((2.0 * j + 1.0) / m - 1.0)
                    a, b = _sphere_row_span(c0 + n0 * s, c1 + n1 * s, c2 + n2 * s, rs, y, focal, width)
                    if a <= b:
                        ua = min(ua, a)
                        ub = max(ub, b)
            ua = max(ua, u0)
            ub = min(ub, u1)
            if gt == 0 or gt == 2 or gt == 3 or gt == 4:
                # The span's distances first, in a branch-free loop the compiler vectorises
                # (the scalar code's operations on every pixel; SIMD square roots and
                # divisions round exactly as scalar ones), then the nearest-hit merge, also
                # branch-free (selects instead of a branch per pixel: 0.66-0.79 -> 0.49-0.66 ms
                # per 283x160 frame of the paper episode, with the planes' spans vectorised).
                # Pixels at the span's ends already hit nearer than this geom can be are skipped
                # by the merge anyway: leave them out of the distances too.
                row = (v - row0) * width
                while ua <= ub and dist[row + ua] >= 0.0 and dist[row + ua] < bound:
                    ua += 1
                while ub >= ua and dist[row + ub] >= 0.0 and dist[row + ub] < bound:
                    ub -= 1
                if ua > ub:
                    continue
                _span_distances(
                    gt, rays_x, rays_y, rays_z, (v - row0) * width, ua, ub, r00, r01, r02, r10, r11, r12, r20, r21, r22,
                    ox, oy, oz, s0, s1, s2, tbuf,
                )  # fmt: skip
                _merge_span(dist, geomid, tbuf, row, ua, ub, bound, cutoff, g)
                continue
            for u in range(ua, ub + 1):
                i = (v - row0) * width + u
                best = dist[i]
                if best >= 0.0 and best < bound:
                    continue  # already hit closer than this geom can be
                ex = rays_x[i]
                ey = rays_y[i]
                ez = rays_z[i]
                dx = r00 * ex + r10 * ey + r20 * ez
                dy = r01 * ex + r11 * ey + r21 * ez
                dz = r02 * ex + r12 * ey + r22 * ez
                t = _cylinder_or_box(gt, size, ox, oy, oz, dx, dy, dz)
                if t >= 0.0 and t <= cutoff and (best < 0.0 or t < best or (t == best and g < geomid[i])):
                    dist[i] = t
                    geomid[i] = g


@njit(cache=True)
def compact_cloud(
    depth,  # (h*w,) per pixel: z-depth, or the ray length when along_ray [m] (-1 / inf / nan: no hit)
    along_ray,  # True: ``depth`` holds ray lengths (the ray caster's), else z-depths (the renderer's)
    geomid,  # (h*w,) geom hit per pixel (-1: none)
    rays_x,  # (h*w,) x of the unit pixel rays in the camera frame, row-major
    rays_y,  # (h*w,) their y
    rays_z,  # (h*w,) their z
    rotation,  # (3, 3) camera rotation (world from camera)
    origin,  # (3,) camera position
    min_depth,
    max_depth,
    stem_range,
    noise,  # (h*w,) standard normal draws for depth noise, or (0,)
    noise_scale,  # depth noise std at 1 m [m]
    keep,  # (h*w,) bool: pixel not dropped out, or (0,)
    geom_ok,  # (ngeom,) bool: geoms the camera may see
    geom_label,  # (ngeom,) int8
    geom_color,  # (ngeom, 3) uint8
    pixel_color,  # (h*w, 3) uint8 rendered colours, or (0, 3)
    stem_label,
    obstacle_label,
    out_points,  # (h*w, 3)
    out_labels,  # (h*w,) int8
    out_colors,  # (h*w, 3) uint8
    out_depth,  # (h*w,)
    out_pixels,  # (h*w, 2) int32
    height,
    width,
):
    """Valid pixels -> world points, labels, colours, z-depths, pixels; returns the number of points written."""
    count = 0
    n = depth.shape[0]
    use_noise = noise.shape[0] == n
    use_keep = keep.shape[0] == n
    use_pixel_color = pixel_color.shape[0] == n
    colors = pixel_color if use_pixel_color else geom_color  # indexed by pixel, or by geom
    # The rotation and origin in scalars: the compiler cannot tell that the outputs do not alias them.
    r00, r01, r02 = rotation[0, 0], rotation[0, 1], rotation[0, 2]
    r10, r11, r12 = rotation[1, 0], rotation[1, 1], rotation[1, 2]
    r20, r21, r22 = rotation[2, 0], rotation[2, 1], rotation[2, 2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for v in range(height):
        for u in range(width):
            i = v * width + u
            g = geomid[i]
            if g < 0 or not geom_ok[g]:
                continue
            rz = rays_z[i]
            z = depth[i] * rz if along_ray else depth[i]
            if not (z >= min_depth and z <= max_depth):
                continue
            if use_keep and not keep[i]:
                continue
            if use_noise:
                # Stereo depth error grows with depth squared (fixed disparity error).
                z = z + noise[i] * noise_scale * z * z
            s = z / rz
            x = rays_x[i] * s
            y = rays_y[i] * s
            zz = rz * s
            out_points[count, 0] = o0 + r00 * x + r01 * y + r02 * zz
            out_points[count, 1] = o1 + r10 * x + r11 * y + r12 * zz
            out_points[count, 2] = o2 + r20 * x + r21 * y + r22 * zz
            label = geom_label[g]
            # Beyond the detection range a stem point is just another obstacle (the paper).
            if label == stem_label and s > stem_range:
                label = obstacle_label
            out_labels[count] = label
            c = i if use_pixel_color else g
            out_colors[count, 0] = colors[c, 0]
            out_colors[count, 1] = colors[c, 1]
            out_colors[count, 2] = colors[c, 2]
            out_depth[count] = z
            out_pixels[count, 0] = v
            out_pixels[count, 1] = u
            count += 1
    return count
