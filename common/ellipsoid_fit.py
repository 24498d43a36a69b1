"""Ellipsoidal shells fitted to surface voxels (Cheung et al. 2000, section 4).

Six shells (torso, head, two arms, two legs) follow the surface voxels of an actor with an
EM-like loop: each voxel goes to the shell whose surface is closest (E step, section 4.1),
then each shell is re-estimated from the moments of its voxels (M step, section 4.2:
centre = mean, axes = eigenvectors of the second-moment matrix). When nothing is known yet,
the activation procedure of section 4.3 starts with one shell over all voxels and adds
shells, at the extremities, until the fit error is small or all six are in use.

The body part (``volume_energy``, ``initial_pose``) fits the articulated body of
``common.body`` to the voxels as Bottino and Laurentini do: a weighted sum of squared
distances from surface voxels to the closest body segment, started from the shells.

One deliberate change to section 4.2: the paper turns eigenvalues into radii with a fixed
factor (M = 4 * covariance), which is exact for no closed surface (a sphere's surface needs
3, a thin rod's length 4). Here the radii are those of the ellipsoid whose *surface*, with
uniform area density, has the measured second moments (a small fixed-point iteration), so a
complete shell is recovered exactly and a partial one stays bounded.

One module of about 840 lines: the shells, the body's volume energy and the staged fit share
the shell distances and the segment ellipsoids; apart, each would import the others.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.ndimage import distance_transform_edt
from scipy.optimize import minimize
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from common.body import (_SEGMENT_PARENTS, JOINT_NAMES, PARAM_LIMITS, BodyModel, _forward_kinematics, _segment_mask,
                         clip_to_limits, forward_kinematics, load_body_model, rest_params)
from common.retarget import heading_tilt

SHELL_NAMES = ("torso", "head", "left_arm", "right_arm", "left_leg", "right_leg")
SHELLS = len(SHELL_NAMES)
MIN_SHELL_POINTS = 8  # a shell with fewer voxels keeps its previous parameters
MIN_RADIUS = 0.01  # metres; keeps flat or tiny point sets from giving singular shells
ACTIVATION_ERROR = 0.03  # metres: activation adds shells while the fit error exceeds this (or a voxel)
ACTIVATION_QUANTILE = 0.95  # the fit error activation looks at: this quantile of distances
CORE_WEIGHT = 0.6  # the core's geodesic distances are scaled by this when seeding shells
GRAPH_REACH = 2.0  # surface voxels this many spacings apart are neighbours (26-connected)
EM_ITERATIONS = 3  # E/M rounds per frame when tracking from the previous frame
EM_POINTS = 1500  # surface voxels the E/M rounds use at most
ACTIVATION_ITERATIONS = 5  # E/M rounds after each activated shell
NEWTON_STEPS = 30  # most iterations of the closest-point solve (monotone, quadratic near the root)
BOUND_SLACK_M = 1e-6  # metres taken off the lower bound of a shell distance before it skips the solve
NEWTON_TOLERANCE = 1e-9  # |F(t) - 1| at which it stops (distance error ~1e-9 of the radii)
MOMENT_STEPS = 8  # fixed-point iterations from surface moments to radii (converges in about 5)
SPHERE_SAMPLES = 512  # quadrature points on the unit sphere for surface moments (error ~1e-4)
FOOT_HEIGHT = 0.12  # metres above the lowest leg voxel that count as the foot
UP = np.array([0.0, 0.0, 1.0])
THOMSEN_P = 1.6075  # Knud Thomsen's exponent for the ellipsoid area (error < 1.1 %)
INIT_POINTS = 400  # surface voxels sampled for the initialisation's energy
INIT_XTOL = 2e-3  # Powell's tolerance on parameters (metres, radians)
INIT_MAXFEV = 200  # energy evaluations per Powell run at most
INIT_STARTS_KEPT = 2  # of a limb's start values, the best (by energy) this many are solved
HULL_WEIGHT = 1.0  # hull_energy relative to Bottino's term (per voxel)
GUARD_WEIGHT = 10.0  # an arm sunk into the trunk, relative to the same depth outside the volume
SEGMENT_SAMPLES = 24  # surface samples per segment ellipsoid for hull_energy
ROBUST_DISTANCE = 0.06  # metres: scale of the bounded loss of the trunk-only stage
SCALE_RANGE = (0.8, 1.25)  # actor height over the model's, accepted at initialisation
CHEST_BAND = (0.62, 0.78)  # fraction of the actor's height where the chest's width is measured
TRUNK_PARAMS = tuple(range(0, 9))  # root + spine
TRUNK_SEGMENTS = (0, 1, 2, 3)  # pelvis, abdomen, chest, head
TRUNK_CORE = [0, 1, 2, 3]  # arms may sink into these no deeper than in the rest pose
ARM_SEGMENTS = (4, 5, 6, 7, 8, 9)
NECK_PARAMS = (9, 10)
# Per limb: (shoulder or hip rotation vector + elbow or knee), the segments they move.
LIMB_GROUPS = {
    "left_arm": ((11, 12, 13, 14), (4, 5, 6)),
    "right_arm": ((17, 18, 19, 20), (7, 8, 9)),
    "left_leg": ((23, 24, 25, 26), (10, 11, 12)),
    "right_leg": ((29, 30, 31, 32), (13, 14, 15)),
}
LIMB_SEGMENTS = {  # parent, upper segment, the next segment (whose joint ends the upper one)
    "left_arm": (2, 4, 5), "right_arm": (2, 7, 8), "left_leg": (0, 10, 11), "right_leg": (0, 13, 14),
}
# Start directions in the parent's frame for a left limb (x mirrored for the right one);
# the model faces -y, z up.
ARM_FAN = ((0.3, 0.0, -1.0), (1.0, 0.0, -0.6), (1.0, 0.0, 0.0), (0.3, -1.0, -0.6), (0.3, 0.6, -1.0),
           (0.3, -1.0, 0.2), (0.5, 0.0, 1.0))
LEG_FAN = ((0.1, 0.0, -1.0), (0.1, -0.6, -1.0), (0.1, 0.5, -1.0), (0.5, 0.0, -1.0), (0.1, -1.0, -0.3))
ARM_BENDS = (0.0, 1.2)  # elbow flexion starts, radians
LEG_BENDS = (0.0, 0.8)  # knee flexion starts


@dataclass(frozen=True)
class EllipsoidFit:
    """Shells of one frame, in SHELL_NAMES order once all six are active and labelled.

    centres (6, 3) metres; axes (6, 3, 3) unit axes as columns, longest first; radii (6, 3)
    metres, descending; active (6,) bool (inactive rows are NaN); assignment (n,) int shell
    of each surface voxel (-1: none); error: RMS distance of the voxels to their shells, metres;
    labelled: rows follow SHELL_NAMES; facing: (3,) the actor's front if known, else None.
    """

    centres: np.ndarray
    axes: np.ndarray
    radii: np.ndarray
    active: np.ndarray
    assignment: np.ndarray
    error: float
    labelled: bool
    facing: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.active.sum())


# ----------------------------------------------------------------------------- geometry

def shell_distances(points, centres, axes, radii) -> np.ndarray:
    """Distance from each point to each ellipsoid surface (inside or outside), metres.

    points (n, 3); centres (E, 3); axes (E, 3, 3) columns; radii (E, 3) -> (n, E).
    Solves for the closest point with Eberly's parametrisation: x_i = r_i^2 y_i / (t + r_i^2)
    where t is the largest root of F(t) = sum (r_i y_i / (t + r_i^2))^2 = 1. F is convex and
    decreasing right of its last pole, so Newton from a point left of the root converges
    monotonically. Compiled: the voxel fit of a first frame calls it some 10,000 times.
    """
    return _shell_distances(np.ascontiguousarray(points, dtype=np.float64),
                            np.ascontiguousarray(centres, dtype=np.float64),
                            np.ascontiguousarray(axes, dtype=np.float64),
                            np.ascontiguousarray(radii, dtype=np.float64), NEWTON_STEPS, NEWTON_TOLERANCE)


@njit(cache=True, nogil=True)
def _shell_distances(points, centres, axes, radii, steps, tolerance):
    n, E = points.shape[0], centres.shape[0]
    out = np.empty((n, E))
    for e in range(E):
        for k in range(n):
            out[k, e] = _shell_distance(points[k], centres[e], axes[e], radii[e], steps, tolerance)
    return out


@njit(cache=True, nogil=True, inline="always")
def _shell_distance(point, centre, axes, r, steps, tolerance) -> float:
    """``shell_distances`` of one point (3,) to one shell: centre (3,), axes (3, 3) columns, radii (3,)."""
    y = np.empty(3)
    t = -np.inf
    for i in range(3):  # the point in the shell's frame, off its symmetry planes
        v = 0.0
        for j in range(3):
            v += (point[j] - centre[j]) * axes[j, i]
        y[i] = max(abs(v), 1e-6 * r[i])
        t = max(t, -r[i] * r[i] + r[i] * y[i])  # each term alone is 1 here, so F >= 1
    for _ in range(steps):
        f, df = -1.0, 0.0
        for i in range(3):
            d = t + r[i] * r[i]
            term = (r[i] * y[i]) ** 2 / (d * d)
            f += term
            df -= 2.0 * term / d
        t -= f / df
        if abs(f) < tolerance:
            break
    dist2 = 0.0
    for i in range(3):  # y - x, x_i = r_i^2 y_i / (t + r_i^2)
        dist2 += (y[i] * t / (t + r[i] * r[i])) ** 2
    return np.sqrt(dist2)


def _unit_sphere(count: int) -> np.ndarray:
    """(count, 3) nearly uniform points on the unit sphere (Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


_SPHERE = _unit_sphere(SPHERE_SAMPLES)
_SEGMENT_SPHERE = _unit_sphere(SEGMENT_SAMPLES)


def surface_variances(radii) -> np.ndarray:
    """(E, 3) radii -> (E, 3) variance along each axis of uniform points on the ellipsoid surface."""
    radii = np.asarray(radii, dtype=np.float64)
    # x = r * s maps the unit sphere onto the ellipsoid; its area element is
    # r1 r2 r3 * |s / r|, so weight each sphere sample by |s / r|.
    w = np.linalg.norm(_SPHERE[None] / radii[:, None, :], axis=-1)  # (E, P)
    x2 = (_SPHERE[None] * radii[:, None, :]) ** 2
    return np.einsum("ep,epi->ei", w, x2) / w.sum(axis=1)[:, None]


def radii_from_variances(variances) -> np.ndarray:
    """(E, 3) principal variances of shell points -> (E, 3) radii whose surface matches them."""
    lam = np.maximum(np.asarray(variances, dtype=np.float64), (MIN_RADIUS ** 2) / 3.0)
    r = np.sqrt(3.0 * lam)  # exact for a sphere
    for _ in range(MOMENT_STEPS):
        r = r * np.sqrt(lam / surface_variances(r))
    return np.maximum(r, MIN_RADIUS)


def moments(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Moment analysis of one shell's points (section 4.2).

    (n, 3) -> centre (3,), axes (3, 3) columns (longest first, first axis upwards,
    right-handed), radii (3,) descending.
    """
    points = np.asarray(points, dtype=np.float64)
    centre = points.mean(axis=0)
    d = points - centre
    axes, radii = _principal(d.T @ d / len(points))
    return centre, axes[0], radii[0]


def _principal(cov) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3, 3) second-moment matrices -> axes (E, 3, 3) columns and radii (E, 3), descending."""
    lam, vec = np.linalg.eigh(np.asarray(cov).reshape(-1, 3, 3))
    radii = radii_from_variances(lam)
    order = np.argsort(-radii, axis=1, kind="stable")
    radii = np.take_along_axis(radii, order, axis=1)
    vec = np.take_along_axis(vec, order[:, None, :], axis=2)
    flip = np.where(vec[:, 2, 0] < 0, -1.0, 1.0)  # first axis upwards (its z component >= 0)
    vec[:, :, 0] *= flip[:, None]
    vec[:, :, 2] = np.cross(vec[:, :, 0], vec[:, :, 1])  # right-handed
    return vec, radii


# ----------------------------------------------------------------------------- EM fitting

def _empty() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (np.full((SHELLS, 3), np.nan), np.full((SHELLS, 3, 3), np.nan), np.full((SHELLS, 3), np.nan))


def _em(points, centres, axes, radii, active, iterations):
    """E/M rounds over the active shells; returns (centres, axes, radii, assignment, error).

    The rounds use at most EM_POINTS evenly strided voxels (fine grids give thousands of
    nearly redundant ones); the final assignment and error cover all of them.
    """
    centres, axes, radii = centres.copy(), axes.copy(), radii.copy()
    idx = np.flatnonzero(active)
    all_points = points
    points = points[::-(-len(points) // EM_POINTS)]
    assignment = None
    for _ in range(iterations):
        dist = shell_distances(points, centres[idx], axes[idx], radii[idx])
        new = idx[np.argmin(dist, axis=1)]
        if assignment is not None and np.array_equal(new, assignment):
            break
        assignment = new
        counts = np.bincount(assignment, minlength=SHELLS)
        fitted = idx[counts[idx] >= MIN_SHELL_POINTS]
        cov = np.empty((len(fitted), 3, 3))
        for j, e in enumerate(fitted):
            sel = points[assignment == e]
            centres[e] = sel.mean(axis=0)
            d = sel - centres[e]
            cov[j] = d.T @ d / len(sel)
        axes[fitted], radii[fitted] = _principal(cov)
    dist = shell_distances(all_points, centres[idx], axes[idx], radii[idx])
    assignment = idx[np.argmin(dist, axis=1)]
    error = float(np.sqrt(np.mean(np.min(dist, axis=1) ** 2)))
    return centres, axes, radii, assignment, error


def fit_ellipsoids(points, previous: EllipsoidFit | None = None, iterations: int = EM_ITERATIONS,
                   activation_error: float = ACTIVATION_ERROR) -> EllipsoidFit:
    """Fit the shells to one frame's surface voxel centres (n, 3).

    With a fully active ``previous`` frame: EM from its shells (tracking). Otherwise the
    activation procedure (``activate``) runs on this frame, so shells appear as soon as the
    actor's pose separates the limbs.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < MIN_SHELL_POINTS:
        raise ValueError(f"need at least {MIN_SHELL_POINTS} surface voxels, got {len(points)}")
    if previous is not None and previous.active.all():
        c, a, r, assignment, error = _em(points, previous.centres, previous.axes, previous.radii,
                                         previous.active, iterations)
        return EllipsoidFit(c, a, r, previous.active.copy(), assignment, error, previous.labelled,
                            _facing(points, assignment, (4, 5)) if previous.labelled else None)
    return activate(points, activation_error)


def activate(points, activation_error: float = ACTIVATION_ERROR) -> EllipsoidFit:
    """Section 4.3: start with one shell over all voxels and add shells while the fit is poor.

    The paper does not say where a new shell starts. Here seeds are the body's core (the
    voxel nearest the centroid) and then, one per added shell, the voxel geodesically
    farthest (along the voxel surface) from all earlier seeds: the extremities (feet, hands,
    head) in turn. Each time, the voxels are split among the seeds by geodesic distance,
    every shell starts from the moments of its part and EM refines them. The fit is poor
    while the ACTIVATION_QUANTILE of the voxels' distances to their shells exceeds
    ``activation_error``.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    graph, spacing = _surface_graph(points)
    limit = max(activation_error, spacing)  # a voxel's quantisation is no reason for a shell
    centres, axes, radii = _empty()
    active = np.zeros(SHELLS, dtype=bool)
    centres[0], axes[0], radii[0] = moments(points)
    active[0] = True
    core = int(np.argmin(np.linalg.norm(points - points.mean(axis=0), axis=1)))
    from_seeds = [_geodesic(graph, points, core)]
    centres, axes, radii, assignment, error = _em(points, centres, axes, radii, active, ACTIVATION_ITERATIONS)
    while _poor(points, centres, axes, radii, active, limit) and not active.all():
        seed = int(np.argmax(np.min(from_seeds, axis=0)))
        from_seeds.append(_geodesic(graph, points, seed))
        active[len(from_seeds) - 1] = True
        # Geodesic Voronoi cells of the seeds, the core's distances shrunk so that it keeps the
        # trunk and the extremities start small (EM grows them along their limbs).
        part = np.argmin([from_seeds[0] * CORE_WEIGHT, *from_seeds[1:]], axis=0)
        for e in np.flatnonzero(active):
            region = points[part == e]
            if len(region) < MIN_SHELL_POINTS:
                region = points[np.argsort(from_seeds[e])[:MIN_SHELL_POINTS]]
            centres[e], axes[e], radii[e] = moments(region)
        centres, axes, radii, assignment, error = _em(points, centres, axes, radii, active,
                                                      ACTIVATION_ITERATIONS)
    fit = EllipsoidFit(centres, axes, radii, active, assignment, error, False)
    return label_shells(points, fit) if active.all() else fit


def _poor(points, centres, axes, radii, active, limit) -> bool:
    idx = np.flatnonzero(active)
    resid = shell_distances(points, centres[idx], axes[idx], radii[idx]).min(axis=1)
    return bool(np.quantile(resid, ACTIVATION_QUANTILE) > limit)


def _geodesic(graph, points, source: int) -> np.ndarray:
    """(n,) distances along the voxel surface from one voxel; straight-line to other pieces."""
    d = dijkstra(graph, directed=False, indices=source)
    apart = ~np.isfinite(d)
    d[apart] = np.linalg.norm(points[apart] - points[source], axis=1)
    return d


def _surface_graph(points):
    """(sparse graph joining surface voxels that touch, voxel spacing in metres)."""
    tree = cKDTree(points)
    spacing = np.median(tree.query(points, k=2)[0][:, 1])
    pairs = tree.query_pairs(GRAPH_REACH * spacing, output_type="ndarray")
    w = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    return coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2).tocsr(), float(spacing)


# ----------------------------------------------------------------------------- labelling

def label_shells(points, fit: EllipsoidFit) -> EllipsoidFit:
    """Reorder six active shells into SHELL_NAMES from their layout.

    torso: the largest shell; head: the shell nearest the torso's upper end; legs: the two
    lowest along the torso axis; arms: the rest. Left and right need the actor's front,
    taken from the feet (the lowest leg voxels reach forward of the shins); without it the
    sides are a consistent but arbitrary choice (see ``facing``).
    """
    c, a, r = fit.centres, fit.axes, fit.radii
    torso = int(np.argmax(np.prod(r, axis=1)))
    up = a[torso][:, 0]  # moments() points the first axis upwards
    top = c[torso] + up * r[torso][0]
    rest = [e for e in range(SHELLS) if e != torso]
    head = min(rest, key=lambda e: np.linalg.norm(c[e] - top))
    rest.remove(head)
    rest.sort(key=lambda e: (c[e] - c[torso]) @ up)
    legs, arms = rest[:2], rest[2:]
    facing = _facing(points, fit.assignment, legs)
    left = np.cross(UP, facing) if facing is not None else _lateral(a[torso])
    arms.sort(key=lambda e: -(c[e] @ left))
    legs.sort(key=lambda e: -(c[e] @ left))
    order = np.array([torso, head, *arms, *legs])
    new_index = np.empty(SHELLS, dtype=np.int64)
    new_index[order] = np.arange(SHELLS)
    assignment = np.where(fit.assignment >= 0, new_index[np.maximum(fit.assignment, 0)], -1)
    return EllipsoidFit(c[order], a[order], r[order], fit.active[order], assignment, fit.error, True, facing)


def _lateral(torso_axes) -> np.ndarray:
    """A horizontal direction across the torso (sign arbitrary but deterministic)."""
    lat = torso_axes[:, 1] - (torso_axes[:, 1] @ UP) * UP
    if np.linalg.norm(lat) < 1e-6:
        lat = np.array([1.0, 0.0, 0.0])
    lat /= np.linalg.norm(lat)
    return lat if lat[0] + 1e-9 * lat[1] >= 0 else -lat


def _facing(points, assignment, legs) -> np.ndarray | None:
    """The actor's horizontal front from the feet: lowest leg voxels minus the shin above them."""
    shifts = []
    for leg in legs:
        p = points[assignment == leg]
        if len(p) < 2 * MIN_SHELL_POINTS:
            continue
        z0 = p[:, 2].min()
        foot = p[p[:, 2] < z0 + FOOT_HEIGHT]
        shin = p[(p[:, 2] >= z0 + 2 * FOOT_HEIGHT) & (p[:, 2] < z0 + 4 * FOOT_HEIGHT)]
        if len(foot) < MIN_SHELL_POINTS or len(shin) < MIN_SHELL_POINTS:
            continue
        shifts.append(foot.mean(axis=0) - shin.mean(axis=0))
    if not shifts:
        return None
    f = np.mean(shifts, axis=0)
    f[2] = 0.0
    n = np.linalg.norm(f)
    return f / n if n > 0.01 else None


# ----------------------------------------------------------------------------- body fitting

def segment_ellipsoids(model: BodyModel, params) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(35,) parameters -> the 16 segments' oriented bounding ellipsoids in the world:
    centres (16, 3), axes (16, 3, 3) columns, radii (16, 3), metres."""
    pose = forward_kinematics(model, params)
    rot, org = pose.rotations[0], pose.origins[0]
    centres = org + np.einsum("sij,sj->si", rot, model.ellipsoid_centres)
    return centres, rot @ model.ellipsoid_axes, np.asarray(model.ellipsoid_radii, dtype=np.float64)


def segment_weights(model: BodyModel) -> np.ndarray:
    """(16,) Bottino's w_j: small segments weigh more, so that limbs count like the trunk.

    w_j = sqrt(mean area / area_j) with each ellipsoid's surface area (Thomsen's formula);
    the square root keeps hands and feet, which voxels resolve worst, from dominating.
    """
    a, b, c = (np.asarray(model.ellipsoid_radii, dtype=np.float64) ** THOMSEN_P).T
    area = 4.0 * np.pi * ((a * b + a * c + b * c) / 3.0) ** (1.0 / THOMSEN_P)
    return np.sqrt(area.mean() / area)


def volume_energy(model: BodyModel, params, points, weights=None) -> float:
    """Bottino's D(phi, R) = sum_j w_j sum_{C in S_j} d_j(C)^2, metres^2.

    params (35,); points (n, 3) voxel centres (surface voxels); S_j: the voxels closest to
    segment j, d_j: distance to its ellipsoid's surface; weights (16,) default
    ``segment_weights``.
    """
    w = segment_weights(model) if weights is None else np.asarray(weights, dtype=np.float64)
    d = shell_distances(points, *segment_ellipsoids(model, params))
    j = np.argmin(d, axis=1)
    return float(np.sum(w[j] * d[np.arange(len(j)), j] ** 2))


def segment_samples(model: BodyModel, params) -> np.ndarray:
    """(16, SEGMENT_SAMPLES, 3) points spread over each segment ellipsoid's surface, metres."""
    return _surface_samples(*segment_ellipsoids(model, params))


def _surface_samples(centres, axes, radii) -> np.ndarray:
    """(E, 3), (E, 3, 3), (E, 3) -> (E, SEGMENT_SAMPLES, 3) points on the ellipsoids."""
    return centres[:, None, :] + np.einsum("sij,spj->spi", axes, _SEGMENT_SPHERE[None] * radii[:, None, :])


@dataclass(frozen=True)
class VolumeTarget:
    """One frame's voxels as the body fit sees them.

    points (n, 3): surface voxel centres (a random subset when there are many);
    outside (N, N, N) float32: distance from each voxel centre to the nearest occupied one,
    metres (0 inside); origin (3,), voxel_size (3,) of the grid.
    """

    points: np.ndarray
    outside: np.ndarray
    origin: np.ndarray
    voxel_size: np.ndarray

    @classmethod
    def from_voxels(cls, voxels, max_points: int = INIT_POINTS, seed: int = 0) -> "VolumeTarget":
        """From a ``common.voxels.VoxelResult`` with surface voxels."""
        points = voxels.surface_points()
        if len(points) > max_points:
            points = points[np.random.default_rng(seed).choice(len(points), max_points, replace=False)]
        outside = distance_transform_edt(~voxels.occupied, sampling=voxels.voxel_size).astype(np.float32)
        return cls(points, outside, voxels.origin, voxels.voxel_size)

    def outside_distance(self, q) -> np.ndarray:
        """(..., 3) points -> (...,) metres to the occupied volume (nearest voxel; beyond the
        grid, plus the distance to it)."""
        q = np.asarray(q, dtype=np.float64)
        shape = np.array(self.outside.shape)
        f = (q - self.origin) / self.voxel_size - 0.5
        idx = np.clip(np.rint(f).astype(np.int64), 0, shape - 1)
        beyond = np.linalg.norm((f - idx) * self.voxel_size * ((f < -0.5) | (f > shape - 0.5)), axis=-1)
        return self.outside[idx[..., 0], idx[..., 1], idx[..., 2]] + beyond


def hull_energy(model: BodyModel, params, target: VolumeTarget, weights=None) -> float:
    """The model-to-volume term the initialisation adds to ``volume_energy``, metres^2.

    Bottino's D only asks every voxel to be near some segment, so a segment may wander off
    into empty space for free; this term charges each segment's surface samples their
    squared distance to the occupied volume, weighted like D and scaled to its voxel count.
    """
    w = segment_weights(model) if weights is None else np.asarray(weights, dtype=np.float64)
    out = target.outside_distance(segment_samples(model, params))
    return float(_hull_scale(target) * np.sum(w[:, None] * out ** 2))


def _hull_scale(target: VolumeTarget) -> float:
    return HULL_WEIGHT * len(target.points) / (16 * SEGMENT_SAMPLES)


@dataclass(frozen=True)
class InitialPose:
    """First-frame initialisation from voxels.

    params (35,) the starting pose for ``model`` (the given actor, or the default one scaled
    by ``scale``);
    heading radians; energy: volume_energy + hull_energy at params; shells: the ellipsoid
    fit it started from; evaluations: energy evaluations spent; candidates (C, 35): every
    solved front/back candidate, the chosen one (``params``) first.
    """

    params: np.ndarray
    model: BodyModel
    scale: float
    heading: float
    energy: float
    shells: EllipsoidFit
    evaluations: int
    candidates: np.ndarray


def initial_pose(voxels, model: BodyModel | None = None, seed: int = 0, score=None) -> InitialPose:
    """Position, heading, scale and a starting pose of a standing actor from one frame's voxels.

    voxels: a ``common.voxels.VoxelResult`` with surface voxels; model: the actor's body,
    whose size is kept (scale 1); without one, the default body is scaled by the actor's
    height over its own (exact for a standing actor only: a crouch looks small). The six
    shells come first (``activate``); the pelvis starts over
    the voxels' centroid at the model's pelvis height; the heading, up to front and back,
    is the widest horizontal direction of the chest (shoulder to shoulder), and both
    candidates are solved. Per candidate, Powell minimises volume_energy + hull_energy in
    stages: the trunk alone against the voxels (robust loss, so the limbs' voxels do not
    pull it); each limb from a fan of directions (and, where labelled, its shell) with the
    rest of the body fixed; the trunk again with all segments; each limb again, from the fan
    and from where it is (a limb solved beside limbs still at rest may have taken their
    voxels); the neck. Starts from shells use the shell of that kind nearest the limb's joint,
    not its label (left and right come from the feet, which can mislead).

    score: optional function from candidates (C, 35) for the returned ``model`` to (C,)
    energies, such as the XOR energy against the frame's silhouettes; given one, it and not
    the volume energy picks between front and back (the volume energy confuses them when
    limbs are bent or hidden, the silhouettes less so).
    """
    base = load_body_model() if model is None else model
    points = voxels.surface_points()
    if len(points) < MIN_SHELL_POINTS:
        raise ValueError(f"need at least {MIN_SHELL_POINTS} surface voxels, got {len(points)}")
    shells = activate(points)
    vz = float(voxels.voxel_size[2])
    floor = points[:, 2].min() - vz / 2
    height = points[:, 2].max() + vz / 2 - floor
    scale = 1.0 if model is not None else float(np.clip(height / base.height, *SCALE_RANGE))
    body = base.scaled(scale) if scale != 1.0 else base
    target = VolumeTarget.from_voxels(voxels, seed=seed)
    weights = segment_weights(body)
    occupied = voxels.centres(voxels.occupied)
    centroid = occupied.mean(axis=0)
    position = (centroid[0], centroid[1], floor + body.joint_rest[0, 2] - body.vertices[:, 2].min())
    lateral = _chest_lateral(occupied, floor, height)
    h = float(np.arctan2(lateral[1], lateral[0]))  # turns the model's left (+x) onto `lateral`
    solved = []
    evaluations = 0
    for heading in (h, h + np.pi):
        p, energy, n = _fit_body(body, rest_params(body, position, heading), target, weights, shells)
        evaluations += n
        solved.append((energy, p))
    if score is not None:
        rank = np.asarray(score(np.array([p for _, p in solved])), dtype=np.float64)
        solved = [solved[i] for i in np.argsort(rank, kind="stable")]
    else:
        solved.sort(key=lambda t: t[0])
    energy, params = solved[0]
    return InitialPose(params, body, scale, float(params[3]), energy, shells, evaluations,
                       np.array([p for _, p in solved]))


HEAD_DOWN_ROLLS = 4  # turns about the trunk's axis tried for a head-down start, evenly spaced


def head_down_starts(model: BodyModel, shells: EllipsoidFit) -> np.ndarray:
    """(HEAD_DOWN_ROLLS, 35) rest poses upside down along the trunk: the spine (pelvis to neck)
    along the largest shell's long axis, pointing down, the trunk's middle at the shell's
    centre, turned HEAD_DOWN_ROLLS ways about that axis.

    Why: ``initial_pose`` and the standing starts assume the head is the trunk's upper end. A
    cartwheel or a handstand has it at the lower end; the shells' axes have no sign, and
    labelling them (``label_shells``) takes the raised leg for the head. 05_06 from source
    frame 150 (hands on the floor, the head at 0.3 m, a foot at 1.5 m): every upright start
    ends 290 mm off or more, with 32% more silhouette energy than the truth's."""
    trunk = int(np.nanargmax(np.prod(shells.radii, axis=1)))
    down = shells.axes[trunk][:, 0] * (-1.0 if shells.axes[trunk][2, 0] > 0 else 1.0)
    across = np.cross(down, UP)
    if np.linalg.norm(across) < 1e-6:  # straight down: any horizontal direction will do
        across = np.array([1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    half_trunk = 0.5 * np.linalg.norm(model.joint_rest[JOINT_NAMES.index("neck")] - model.joint_rest[0])
    starts = []
    for roll in np.arange(HEAD_DOWN_ROLLS) * (2.0 * np.pi / HEAD_DOWN_ROLLS):
        left = np.cos(roll) * across + np.sin(roll) * np.cross(down, across)
        rotation = np.stack([left, np.cross(down, left), down], axis=-1)  # model x (left), y, z (spine)
        heading, tilt = heading_tilt(rotation[None])
        start = rest_params(model, position=shells.centres[trunk] - down * half_trunk, heading=float(heading[0]))
        start[4:6] = tilt[0]
        starts.append(clip_to_limits(start))
    return np.array(starts)


def _depth_inside(samples, centres, axes, radii) -> np.ndarray:
    """(S, P, 3) points, E ellipsoids -> (S, P) approximate depth inside the deepest one, metres."""
    if samples.size == 0:
        return np.zeros(samples.shape[:2])
    rel = np.einsum("spek,eki->spei", samples[:, :, None, :] - centres[None, None], axes) / radii
    rho = np.linalg.norm(rel, axis=-1)  # < 1 inside
    return np.max(np.maximum(1.0 - rho, 0.0) * radii.min(axis=1), axis=-1)


def _chest_lateral(occupied, floor: float, height: float) -> np.ndarray:
    """(3,) the widest horizontal direction of the occupied voxels at chest height."""
    z = (occupied[:, 2] - floor) / height
    chest = occupied[(z > CHEST_BAND[0]) & (z < CHEST_BAND[1])]
    if len(chest) < 3:
        chest = occupied
    xy = chest[:, :2] - chest[:, :2].mean(axis=0)
    vec = np.linalg.eigh(xy.T @ xy)[1][:, -1]
    return np.array([vec[0], vec[1], 0.0])


def _aim(model: BodyModel, params, limb, direction) -> np.ndarray:
    """Rotation vector of a limb's root joint pointing its upper segment along ``direction``
    (world), given the parent's orientation in ``params``."""
    parent, upper, child = LIMB_SEGMENTS[limb]
    rot = forward_kinematics(model, params).rotations[0][parent]
    rest = model.joint_rest[child] - model.joint_rest[upper]
    rest = rest / np.linalg.norm(rest)
    want = rot.T @ (np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction))
    axis = np.cross(rest, want)
    s, c = np.linalg.norm(axis), float(rest @ want)
    return axis / s * np.arctan2(s, c) if s > 1e-9 else np.zeros(3)


def _limb_starts(model: BodyModel, params, limb: str, shells: EllipsoidFit) -> list[np.ndarray]:
    """Start values (shoulder or hip rotation vector + elbow or knee) for one limb: a fan of
    directions in the parent's frame, each straight and bent, plus its shell's axis."""
    parent = LIMB_SEGMENTS[limb][0]
    rot = forward_kinematics(model, params).rotations[0][parent]
    side = 1.0 if limb.startswith("left") else -1.0
    fan = ARM_FAN if limb.endswith("arm") else LEG_FAN
    bends = ARM_BENDS if limb.endswith("arm") else LEG_BENDS
    starts = []
    for d in fan:
        aim = _aim(model, params, limb, rot @ (np.array(d) * [side, 1.0, 1.0]))
        starts += [np.concatenate([aim, [b]]) for b in bends]
    if shells.labelled:
        # The shell of this kind of limb nearest the joint: the labels' left and right rest on
        # the feet's direction, which can be wrong, and a start through the trunk is no start.
        joint = forward_kinematics(model, params).joints[0][LIMB_SEGMENTS[limb][1]]
        kind = [e for e, name in enumerate(SHELL_NAMES) if name.endswith(limb[-3:])]
        e = min(kind, key=lambda k: np.linalg.norm(shells.centres[k] - joint))
        u = shells.axes[e][:, 0]
        if u @ (shells.centres[e] - joint) < 0:
            u = -u
        starts.append(np.concatenate([_aim(model, params, limb, u), [0.0]]))
        starts.append(np.concatenate([_aim(model, params, limb, shells.centres[e] - joint), [0.0]]))
    return starts


def _fit_body(model: BodyModel, params, target: VolumeTarget, weights, shells: EllipsoidFit):
    """The staged Powell fit of ``initial_pose`` from one start; returns (params, energy, evaluations)."""
    p = np.array(params, dtype=np.float64)
    c, a, r = segment_ellipsoids(model, rest_params(model))
    rest_depth = np.zeros((16, SEGMENT_SAMPLES))
    arms = list(ARM_SEGMENTS)
    rest_depth[arms] = _depth_inside(_surface_samples(c[arms], a[arms], r[arms]), c[TRUNK_CORE], a[TRUNK_CORE],
                                     r[TRUNK_CORE])
    n = 0
    p, _, k = _solve(model, p, TRUNK_PARAMS, TRUNK_SEGMENTS, target, weights, rest_depth, [p[list(TRUNK_PARAMS)]],
                     robust=True)
    n += k
    for polish in (False, True):
        if polish:  # the trunk again, now that the limbs explain their voxels
            p, _, k = _solve(model, p, TRUNK_PARAMS, tuple(range(16)), target, weights, rest_depth,
                             [p[list(TRUNK_PARAMS)]])
            n += k
        for limb, (idx, segments) in LIMB_GROUPS.items():
            # again with the fan: a limb first solved beside limbs still at rest may have
            # taken their voxels; the current value stays among the solved starts
            starts = _limb_starts(model, p, limb, shells)
            p, _, k = _solve(model, p, idx, segments, target, weights, rest_depth, starts,
                             keep=p[list(idx)] if polish else None)
            n += k
    p, _, k = _solve(model, p, NECK_PARAMS, (3,), target, weights, rest_depth, [p[list(NECK_PARAMS)]])
    n += k
    return p, volume_energy(model, p, target.points, weights) + hull_energy(model, p, target, weights), n


def _solve(model: BodyModel, p, idx, segments, target: VolumeTarget, weights, rest_depth, starts,
           robust: bool = False, keep=None):
    """Powell over p[idx] moving ``segments``; returns (params, energy, evaluations).

    Distances to the other segments are fixed while these move, so only the moving ones are
    measured (the pre-rendering idea of the XOR energy, in 3D). ``robust``: fit the segments
    alone with a bounded loss (Geman-McClure, scale ROBUST_DISTANCE), ignoring the rest.
    Several starts: all are ranked by their energy, the best INIT_STARTS_KEPT are solved,
    and ``keep`` too where given (so a second pass never ends worse than it began).
    The energy adds, for arm segments, their samples' depth inside the trunk beyond
    ``rest_depth`` (16, SEGMENT_SAMPLES), GUARD_WEIGHT times the hull term's rate: an arm
    hidden in the trunk's voxels costs nothing in D or the hull term, but an arm does not
    pass through the chest.
    """
    idx = np.array(idx)
    lo, hi = PARAM_LIMITS[idx, 0], PARAM_LIMITS[idx, 1]
    problem = _objective_problem(model, p, segments, target, weights, rest_depth, robust)
    count = [0]

    def energy(x):
        count[0] += 1
        q = p.copy()
        q[idx] = np.clip(x, lo, hi)
        return _solve_objective(q, *problem)

    ranked = sorted(starts, key=energy)[:INIT_STARTS_KEPT] if len(starts) > 1 else starts
    if keep is not None:
        ranked = [keep, *ranked]
    best = None
    for x0 in ranked:
        res = minimize(energy, x0, method="Powell", options={"xtol": INIT_XTOL, "ftol": 1e-6, "maxfev": INIT_MAXFEV})
        if best is None or res.fun < best.fun:
            best = res
    out = p.copy()
    out[idx] = np.clip(best.x, lo, hi)
    return out, float(best.fun), count[0]


def _objective_problem(model: BodyModel, p, segments, target: VolumeTarget, weights, rest_depth, robust: bool,
                       hull_scale: float | None = None) -> tuple:
    """The arguments after the pose of ``_solve_objective`` for moving ``segments`` from the pose
    p (35,): the other segments' distances fixed at p (none with ``robust``); ``hull_scale``
    (default ``_hull_scale(target)``) weighs the hull and guard terms."""
    seg = np.array(segments)
    points = np.ascontiguousarray(target.points, dtype=np.float64)
    fixed = np.full(len(points), np.inf)
    still = np.setdiff1d(np.arange(16), seg)
    if still.size and not robust:
        c, a, r = segment_ellipsoids(model, p)
        fixed = (shell_distances(points, c[still], a[still], r[still]) ** 2 * weights[still]).min(axis=1)
    guarded = seg[np.isin(seg, ARM_SEGMENTS)]
    trunk = np.array(TRUNK_CORE, dtype=np.int64)
    rest_offsets, param_joint, param_axis, offsets, head_top_offset = model.kinematic_tables
    return (rest_offsets, param_joint, param_axis, _SEGMENT_PARENTS, offsets, head_top_offset,
            _segment_mask(tuple(int(i) for i in (*seg, *trunk))),
            np.ascontiguousarray(model.ellipsoid_centres, dtype=np.float64),
            np.ascontiguousarray(model.ellipsoid_axes, dtype=np.float64),
            np.ascontiguousarray(model.ellipsoid_radii, dtype=np.float64),
            seg.astype(np.int64), guarded.astype(np.int64), trunk, points, fixed,
            np.ascontiguousarray(weights, dtype=np.float64), bool(robust),
            float(_hull_scale(target) if hull_scale is None else hull_scale),
            np.ascontiguousarray(rest_depth[guarded], dtype=np.float64), _SEGMENT_SPHERE,
            np.ascontiguousarray(target.outside, dtype=np.float32),
            np.asarray(target.origin, dtype=np.float64), np.asarray(target.voxel_size, dtype=np.float64))


@njit(cache=True, nogil=True)
def _solve_objective(q, rest_offsets, param_joint, param_axis, parents, offsets, head_top_offset, needed,
                     local_centres, local_axes, radii, seg, guarded, trunk, points, fixed, weights, robust, hull,
                     allowed, sphere, outside, origin, voxel_size) -> float:
    """``_solve``'s energy of the pose q (35,), compiled (a first frame's voxel fit evaluates it
    some 10,000 times; numpy's glue cost twice its arithmetic): D over the moving ``seg``
    against the ``fixed`` (n,) weighted squared distances of the others (or ``robust``: the
    bounded loss of ``seg`` alone), plus ``hull`` times the surface samples' squared distances
    to the volume (``VolumeTarget.outside_distance``) and, for the ``guarded`` arm segments,
    GUARD_WEIGHT times their depth inside the ``trunk`` segments beyond ``allowed`` (G, P)."""
    rot, org, _ = _forward_kinematics(q.reshape(1, -1), rest_offsets, param_joint, param_axis, parents, offsets,
                                      head_top_offset, needed)
    centres = np.empty((16, 3))
    axes = np.empty((16, 3, 3))
    for s in range(16):
        if needed[s]:
            for i in range(3):
                centres[s, i] = org[0, s, i] + (rot[0, s, i, 0] * local_centres[s, 0] + rot[0, s, i, 1]
                                                * local_centres[s, 1] + rot[0, s, i, 2] * local_centres[s, 2])
                for j in range(3):
                    axes[s, i, j] = (rot[0, s, i, 0] * local_axes[s, 0, j] + rot[0, s, i, 1] * local_axes[s, 1, j]
                                     + rot[0, s, i, 2] * local_axes[s, 2, j])
    # a shell's distance is only solved for where it can be the point's lowest: |p - centre| less
    # the largest radius (outside) or the smallest radius less it (inside) bounds it from below
    # (less BOUND_SLACK_M, far beyond the solve's error), so the sum is the same as solving all
    reach = np.empty(seg.shape[0])
    core = np.empty(seg.shape[0])
    for m in range(seg.shape[0]):
        reach[m] = max(radii[seg[m], 0], radii[seg[m], 1], radii[seg[m], 2])
        core[m] = min(radii[seg[m], 0], radii[seg[m], 1], radii[seg[m], 2])
    data = 0.0
    for k in range(points.shape[0]):
        d2 = np.inf
        for m in range(seg.shape[0]):
            s = seg[m]
            rho = np.sqrt((points[k, 0] - centres[s, 0]) ** 2 + (points[k, 1] - centres[s, 1]) ** 2
                          + (points[k, 2] - centres[s, 2]) ** 2)
            low = max(rho - reach[m], core[m] - rho, 0.0) - BOUND_SLACK_M
            if low > 0.0 and low * low * weights[s] >= (d2 if robust else min(d2, fixed[k])):
                continue
            dist = _shell_distance(points[k], centres[s], axes[s], radii[s], NEWTON_STEPS, NEWTON_TOLERANCE)
            d2 = min(d2, dist * dist * weights[s])
        if robust:
            data += ROBUST_DISTANCE ** 2 * d2 / (d2 + ROBUST_DISTANCE ** 2)
        else:
            data += min(fixed[k], d2)
    shape = outside.shape
    sample = np.empty(3)
    cell = np.empty(3, np.int64)
    surface = 0.0
    guard = 0.0
    g = 0
    for s in seg:
        is_guarded = g < guarded.shape[0] and guarded[g] == s
        for n in range(sphere.shape[0]):
            for i in range(3):
                sample[i] = centres[s, i] + (axes[s, i, 0] * (sphere[n, 0] * radii[s, 0]) + axes[s, i, 1]
                                             * (sphere[n, 1] * radii[s, 1]) + axes[s, i, 2] * (sphere[n, 2] * radii[s, 2]))
            beyond = 0.0
            for i in range(3):
                f = (sample[i] - origin[i]) / voxel_size[i] - 0.5
                cell[i] = min(max(int(np.rint(f)), 0), shape[i] - 1)
                if f < -0.5 or f > shape[i] - 0.5:
                    beyond += ((f - cell[i]) * voxel_size[i]) ** 2
            out = float(outside[cell[0], cell[1], cell[2]]) + np.sqrt(beyond)
            surface += weights[s] * out * out
            if is_guarded:
                depth = 0.0
                for e in trunk:
                    rho2 = 0.0
                    for i in range(3):
                        rel = 0.0
                        for j in range(3):
                            rel += (sample[j] - centres[e, j]) * axes[e, j, i]
                        rho2 += (rel / radii[e, i]) ** 2
                    depth = max(depth, max(1.0 - np.sqrt(rho2), 0.0) * min(radii[e, 0], radii[e, 1], radii[e, 2]))
                inside = max(depth - allowed[g, n], 0.0)
                guard += weights[s] * inside * inside
        if is_guarded:
            g += 1
    return data + hull * (surface + GUARD_WEIGHT * guard)
