"""Marker-layout design: where to put physical markers so the contractions are observable.

The solve recovers contractions ``x`` from marker displacements ``d_j = sum_i x_i d_ij``, upper-face
muscles from upper-face markers and lower-face muscles from lower-face markers. A layout is good when
each region's displacement matrix ``D_r (3 n_r, m_r)`` (markers x muscles of that region) is well
conditioned, and stays so when a marker is occluded.

:func:`design_markers` picks face-marker sites greedily, per region (the regions the solver splits
the muscles by), under a minimum spacing between markers (face markers and head markers alike). The
score (:func:`_score`) is D-optimal, ``(1/m) log det(D_r^T D_r)``, plus a robustness term (the
first-order change of that log-determinant when markers go missing at random: a direction carried by
a single marker is punished) and a conditioning term (``log lambda_min`` and, weakly, ``-log
lambda_max``). Each step scores, in full, the candidates with the largest D-optimal gain
``log det(I_3 + A_k F^-1 A_k^T)`` (``A_k (3, m_r)`` its displacement rows, ``F`` the information so
far). Markers are then swapped in until every muscle is seen by at least ``min_observers`` markers,
and single-marker exchanges (Fedorov) improve the score while keeping spacing and observers.
(A pure conditioning criterion buys a low condition number by avoiding the most informative sites,
which costs the solve accuracy; a pure A-optimal one concentrates a muscle on one marker and loses it
under occlusion.) Candidates are triangle centroids on the front of the face (normal
towards +z, the cameras' side) that move with expression. The region of a candidate comes from a
horizontal boundary between the upper and lower face, fitted to where upper and lower muscles move
the surface. Rigid head markers (role ``head``) go on well-spread front-facing sites of the upper
face that barely move with any element (upper forehead, temples, nose bridge).

With a camera rig (:class:`~livebridge.face.rig_visibility.RigVisibility`), face and head sites are only those
that enough of the rig's cameras see well at the neutral pose, with a margin for head motion: a marker a camera
sees at a grazing angle, or not at all, is a marker that is often seen by fewer than two cameras and then cannot
be reconstructed. The layout and the rig are designed together, as on a face-capture rig.

:func:`farthest_point_markers` is the baseline (farthest-point sampling of the same candidates), and
:func:`layout_report` gives the figures: condition numbers of the whole face and of each region, the
worst of them with any one marker lost, how many markers observe each muscle and, for a rig, how many
cameras see each marker.
"""

from __future__ import annotations

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import REGIONS, Basis
from livebridge.face.markers import MarkerSet
from livebridge.face.meshio import triangle_areas, triangle_normals
from livebridge.face.rig_visibility import RigVisibility

OBSERVE_FRACTION = 0.2  # a marker observes a muscle that moves it by >= this share of the muscle's peak ...
OBSERVE_MIN_MM = 0.5  # ... and by at least this many mm
MIN_FACING = 0.3  # candidates' normals point towards the cameras (+z) at least this much
DROPOUT_WEIGHT = 1.0  # weight of the marker-loss term of the design score (see _score)
FLOOR_WEIGHT = 1.0  # weight of log lambda_min in the design score
CEILING_WEIGHT = 0.25  # weight of -log lambda_max in the design score
POOL = 256  # candidates (largest D-optimal gains) scored in full at each step
EXCHANGE_PASSES = 3  # sweeps of single-marker exchanges after the greedy design
def region_boundary(basis: Basis) -> float:
    """Height ``y`` (mm) of the horizontal boundary between the upper and the lower face.

    Each vertex votes for the region whose muscles move it more (weight: that motion, squared);
    the boundary is the height that misplaces the least weight. A basis with muscles in only one
    region gets a boundary below (or above) every vertex.
    """
    upper = basis.region_mask("upper")
    energy = np.einsum("mvd,mvd->mv", basis.elements, basis.elements)  # (M, V)
    e_upper = energy[upper].sum(axis=0)
    e_lower = energy[~upper].sum(axis=0)
    y = basis.neutral[:, 1]
    if not upper.any():
        return float(y.max() + 1.0)
    if upper.all():
        return float(y.min() - 1.0)
    is_upper = e_upper > e_lower
    weight = np.maximum(e_upper, e_lower)
    order = np.argsort(y)
    ys, up, w = y[order], is_upper[order], weight[order]
    # boundary just above ys[k]: vertices 0..k are "lower"; cost = upper weight below + lower weight above
    cost = np.cumsum(np.where(up, w, 0.0)) + (np.sum(np.where(~up, w, 0.0)) - np.cumsum(np.where(~up, w, 0.0)))
    k = int(np.argmin(cost))
    return float(0.5 * (ys[k] + ys[min(k + 1, len(ys) - 1)]))


def _triangle_displacements(basis: Basis) -> np.ndarray:
    """Displacement of every triangle centroid by every element, shape (n_triangles, n_muscles, 3)."""
    return np.transpose(basis.elements[:, basis.triangles].mean(axis=2), (1, 0, 2))


def observer_thresholds(basis: Basis) -> np.ndarray:
    """Per muscle, the displacement (mm) at which a marker counts as observing it, shape (n_muscles,)."""
    peak = np.linalg.norm(basis.elements, axis=2).max(axis=1)
    return np.maximum(OBSERVE_FRACTION * peak, OBSERVE_MIN_MM)


def face_candidates(basis: Basis, rig: RigVisibility | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate face-marker sites: triangle centroids that move with expression and face the cameras.

    Parameters
    ----------
    basis : Basis
    rig : RigVisibility, optional
        Sites must be seen by the rig as it asks; without one, their normals must point towards +z
        (at least :data:`MIN_FACING`), where cameras usually stand.

    Returns
    -------
    triangles : ndarray of int, shape (n_candidates,)
    centroids : ndarray, shape (n_candidates, 3)
        Neutral positions, mm.
    regions : ndarray of str, shape (n_candidates,)
    """
    centroids = basis.neutral[basis.triangles].mean(axis=1)
    normals = triangle_normals(basis.neutral, basis.triangles)
    motion = np.linalg.norm(_triangle_displacements(basis), axis=2)  # (T, M)
    moves = (motion >= observer_thresholds(basis)[None]).any(axis=1)
    keep = np.flatnonzero(moves)
    if rig is None:
        keep = keep[normals[keep, 2] >= MIN_FACING]
    else:
        keep = keep[rig.seen(basis, centroids[keep], normals[keep]).sum(axis=0) >= rig.min_views]
    boundary = region_boundary(basis)
    regions = np.where(centroids[keep, 1] > boundary, "upper", "lower")
    return keep, centroids[keep], regions


def default_spacing(basis: Basis, count: int, rig: RigVisibility | None = None) -> float:
    """A minimum spacing (mm) that lets ``count`` markers spread over the candidate area (the one ``rig`` sees)."""
    triangles, _, _ = face_candidates(basis, rig)
    area = triangle_areas(basis.neutral, basis.triangles[triangles]).sum()
    return float(0.55 * np.sqrt(area / max(count, 1)))


def _allocate(counts: dict[str, int], total: int) -> dict[str, int]:
    """Split ``total`` markers between regions in proportion to their muscle counts."""
    present = {r: c for r, c in counts.items() if c > 0}
    shares = {r: total * c / sum(present.values()) for r, c in present.items()}
    alloc = {r: int(np.floor(s)) for r, s in shares.items()}
    for r in sorted(shares, key=lambda r: shares[r] - alloc[r], reverse=True)[: total - sum(alloc.values())]:
        alloc[r] += 1
    return alloc


def _d_gain(rows: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """D-optimal gain ``log det(I_3 + A_k F^-1 A_k^T)`` of adding each candidate, shape (n,).

    Parameters
    ----------
    rows : ndarray, shape (n, 3, m)
        Candidates' displacement rows ``A_k``.
    inverse : ndarray, shape (m, m)
        ``F^-1``, the inverse of the information so far.
    """
    inner = rows @ inverse @ rows.transpose(0, 2, 1) + np.eye(3)
    return np.linalg.slogdet(inner)[1]


def _score(information: np.ndarray, chosen_rows: np.ndarray, candidate_rows: np.ndarray) -> np.ndarray:
    """Design score (higher is better) of the layouts ``chosen + one candidate``, shape (n,).

    With ``F = information + A_c^T A_c`` (``A_c`` the candidate's rows) and ``H_j = A_j F^-1 A_j^T`` the
    leverage of marker ``j`` (``I - H_j`` is what is left of the information along ``A_j`` without it)::

        score = (1/m) log det F                      D-optimal: signal in every direction
              + (w/m) sum_j log det(I_3 - H_j)       robustness: marker j lost
              + FLOOR_WEIGHT log lambda_min(F)        the weakest direction (whole-face conditioning)
              - CEILING_WEIGHT log lambda_max(F)

    The robustness term is the first-order change of ``E[log det F]`` when each marker is missing with
    probability ``w``: it punishes a direction carried by one marker (``H_j -> I``), which costs the solve
    most when that marker is occluded. ``w = DROPOUT_WEIGHT`` is larger than the dropout rate we design for
    (10%), to stand in for the double losses that a first-order term does not see. The two eigenvalue terms
    trade a little determinant for a much better condition number.

    Parameters
    ----------
    information : ndarray, shape (m, m)
        ``ridge I + sum_j A_j^T A_j`` over the chosen markers.
    chosen_rows : ndarray, shape (s, 3, m)
    candidate_rows : ndarray, shape (n, 3, m)
    """
    n, _, m = candidate_rows.shape
    full = information[None] + _outer(candidate_rows)
    eigen = np.maximum(np.linalg.eigvalsh(full), 1e-300)
    score = np.log(eigen).mean(axis=1) + FLOOR_WEIGHT * np.log(eigen[:, 0]) - CEILING_WEIGHT * np.log(eigen[:, -1])
    rows = np.concatenate([np.broadcast_to(chosen_rows, (n,) + chosen_rows.shape), candidate_rows[:, None]], axis=1)
    projected = rows @ np.linalg.inv(full)[:, None]
    leverage = projected @ rows.swapaxes(-1, -2)
    left = np.linalg.slogdet(np.eye(3) * (1 + 1e-12) - leverage)[1]
    return score + DROPOUT_WEIGHT * left.sum(axis=1) / m


def _outer(rows: np.ndarray) -> np.ndarray:
    """``A_k^T A_k`` of rows (n, 3, m), shape (n, m, m) (batched BLAS: numpy's einsum took 3 of the 4 s a
    64-marker design of the built-in face took, which every process that simulates a rig pays)."""
    return rows.transpose(0, 2, 1) @ rows


def _best(rows: np.ndarray, information: np.ndarray, chosen: list[int], options: np.ndarray, keep: int | None = None):
    """Best of ``options`` to add to ``chosen`` by :func:`_score`, on a pool of the best D-optimal gains.

    Returns ``(score, candidate)``; ``keep`` (a candidate) is always scored, so a caller can compare.
    """
    gain = _d_gain(rows[options], np.linalg.inv(information))
    pool = options[np.argsort(-gain, kind="stable")[:POOL]]
    if keep is not None and keep not in pool:
        pool = np.append(pool, keep)
    scores = _score(information, rows[chosen], rows[pool])
    best = int(np.argmax(scores))
    return float(scores[best]), int(pool[best]), (float(scores[np.flatnonzero(pool == keep)[0]]) if keep is not None
                                                   else None)


def _greedy_design(rows: np.ndarray, centroids: np.ndarray, count: int, spacing: float, ridge: float) -> list[int]:
    """Greedy choice of ``count`` candidates at least ``spacing`` apart, maximising :func:`_score`.

    Until the information can have full rank (``3 s < m + 3``) each step takes the largest D-optimal
    gain; from then on, the best :func:`_score` among the :data:`POOL` largest gains.

    Parameters
    ----------
    rows : ndarray, shape (n_candidates, 3, m)
        Each candidate's displacement rows ``A_k`` for the region's muscles.
    centroids : ndarray, shape (n_candidates, 3)
    """
    n, _, m = rows.shape
    information = ridge * np.eye(m)
    allowed = np.ones(n, dtype=bool)
    chosen: list[int] = []
    for _ in range(count):
        options = np.flatnonzero(allowed)
        if not options.size:
            break
        if 3 * len(chosen) < m + 3:
            best = int(options[np.argmax(_d_gain(rows[options], np.linalg.inv(information)))])
        else:
            best = _best(rows, information, chosen, options)[1]
        chosen.append(best)
        information = information + rows[best].T @ rows[best]
        allowed &= np.linalg.norm(centroids - centroids[best], axis=1) >= spacing
    return chosen


def _far(centroids: np.ndarray, sites: list[int], spacing: float) -> np.ndarray:
    """Candidates at least ``spacing`` from every one of ``sites``, shape (n_candidates,) bool."""
    far = np.ones(len(centroids), dtype=bool)
    for c in sites:
        far &= np.linalg.norm(centroids - centroids[c], axis=1) >= spacing
    return far


def _ensure_observers(rows, observes, centroids, chosen, spacing, k_observers, ridge):
    """Swap markers until every muscle has ``k_observers`` observers (where the candidates allow it).

    Each swap brings in a candidate observing the most starved muscle in place of a chosen marker whose
    loss starves no other muscle, choosing the pair with the best :func:`_score`; spacing is kept.
    """
    chosen = list(chosen)
    m = observes.shape[1]
    outer = _outer(rows)
    need = np.minimum(k_observers, observes.sum(axis=0))  # cannot ask more than the candidates offer
    for _ in range(4 * m * k_observers):
        counts = observes[chosen].sum(axis=0)
        starved = np.flatnonzero(counts < need)
        if not starved.size:
            break
        muscle = int(starved[np.argmin(counts[starved] - need[starved])])
        best = None
        for drop in range(len(chosen)):
            if observes[chosen[drop]][counts <= need].any():
                continue  # dropping it would starve a muscle
            rest = chosen[:drop] + chosen[drop + 1:]
            options = np.flatnonzero(_far(centroids, rest, spacing) & observes[:, muscle])
            if not options.size:
                continue
            score, candidate, _ = _best(rows, ridge * np.eye(m) + outer[rest].sum(axis=0), rest, options)
            if best is None or score > best[0]:
                best = (score, drop, candidate)
        if best is None:
            break
        chosen[best[1]] = best[2]
    return chosen


def _exchange(rows, observes, centroids, chosen, spacing, k_observers, ridge, passes=EXCHANGE_PASSES):
    """Improve a layout by single exchanges (Fedorov): replace each marker by the best site for it.

    A marker is replaced when another site, at least ``spacing`` from the other markers, scores better by
    :func:`_score` and the swap leaves every muscle its ``k_observers`` observers. Stops after ``passes``
    sweeps over the markers or a sweep without a change.
    """
    chosen = list(chosen)
    m = observes.shape[1]
    outer = _outer(rows)
    need = np.minimum(k_observers, observes.sum(axis=0))
    distance = np.linalg.norm(centroids[:, None] - centroids[chosen][None], axis=2)  # (n_candidates, s)
    for _ in range(passes):
        changed = False
        for i, current in enumerate(chosen):
            rest = chosen[:i] + chosen[i + 1:]
            allowed = np.delete(distance, i, axis=1).min(axis=1, initial=np.inf) >= spacing
            short = observes[rest].sum(axis=0) < need
            if short.any():
                allowed &= observes[:, short].all(axis=1)
            allowed[current] = True
            score, candidate, now = _best(rows, ridge * np.eye(m) + outer[rest].sum(axis=0), rest,
                                          np.flatnonzero(allowed), keep=current)
            if candidate != current and score > now + 1e-6:
                chosen[i] = candidate
                distance[:, i] = np.linalg.norm(centroids - centroids[candidate], axis=1)
                changed = True
        if not changed:
            break
    return chosen


def _marker_set(triangles, regions, names, roles) -> MarkerSet:
    n = len(triangles)
    return MarkerSet(tuple(names), np.asarray(triangles, dtype=np.int64), np.full((n, 3), 1.0 / 3.0),
                     tuple(regions), tuple(roles))


def _face_names(regions) -> list[str]:
    counter = {r: 0 for r in REGIONS}
    names = []
    for region in regions:
        counter[region] += 1
        names.append(f"{region}_{counter[region]:02d}")
    return names


def head_markers(basis: Basis, n_head: int = 5, rig: RigVisibility | None = None) -> MarkerSet:
    """Rigid head-rig markers: well spread, front-facing sites of the upper face that barely move.

    Sites are triangle centroids above the region boundary (anywhere, when there are too few) that face
    the cameras (normal towards +z, or seen as ``rig`` asks) and whose largest displacement over all
    elements is in the lowest fifth; among them, farthest-point sampling (from the stillest) spreads
    ``n_head`` markers, which are therefore not coplanar on a curved head.

    Raises
    ------
    InputError
        When ``rig`` sees fewer than ``n_head`` sites.
    """
    if n_head < 0:
        raise ValueError("n_head must be >= 0")
    if n_head == 0:
        return _marker_set([], [], [], [])
    centroids = basis.neutral[basis.triangles].mean(axis=1)
    normals = triangle_normals(basis.neutral, basis.triangles)
    motion = np.linalg.norm(_triangle_displacements(basis), axis=2).max(axis=1)
    if rig is None:
        facing = normals[:, 2] >= 0.2
    else:
        facing = rig.seen(basis, centroids, normals).sum(axis=0) >= rig.min_views
        if facing.sum() < n_head:
            raise InputError(f"{n_head} head markers asked for, but only {int(facing.sum())} sites of the face are "
                             f"{rig.describe()}", field="n_head")
    front = np.flatnonzero(facing & (centroids[:, 1] > region_boundary(basis)))
    if len(front) < n_head:
        front = np.flatnonzero(facing)
    still = front[motion[front] <= np.quantile(motion[front], 0.2)]
    if len(still) < n_head:
        still = front[np.argsort(motion[front])[: max(n_head, 1)]]
    picked = [int(still[np.argmin(motion[still])])]
    distance = np.linalg.norm(centroids[still] - centroids[picked[0]], axis=1)
    for _ in range(n_head - 1):
        nxt = int(still[np.argmax(distance)])
        picked.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(centroids[still] - centroids[nxt], axis=1))
    return _marker_set(picked, ["upper"] * n_head, [f"head_{k + 1:02d}" for k in range(n_head)], ["head"] * n_head)


def _join(face: MarkerSet, head: MarkerSet) -> MarkerSet:
    return MarkerSet(face.names + head.names, np.concatenate([face.triangles, head.triangles]),
                     np.concatenate([face.barycentric, head.barycentric]), face.regions + head.regions,
                     face.roles + head.roles)


def design_markers(basis: Basis, count: int = 64, min_spacing_mm: float | None = None, n_head: int = 5,
                   seed: int = 0, min_observers: int = 3, rig: RigVisibility | None = None) -> MarkerSet:
    """Design a marker layout: ``count`` face markers (robust greedy D-optimal per region) plus head markers.

    Parameters
    ----------
    basis : Basis
    count : int
        Number of face markers, split between regions in proportion to their muscle counts.
    min_spacing_mm : float, optional
        Minimum distance between face markers, and from face markers to head markers
        (default: :func:`default_spacing`).
    n_head : int
        Rigid head-rig markers (>= 4 for a robust head pose; 0 for none).
    seed : int
        Breaks ties only; the design is deterministic for a given basis.
    min_observers : int
        Every muscle should be observed by at least this many markers of its region.
    rig : RigVisibility, optional
        The camera rig the layout is for: face and head markers go only where it sees them as it asks.

    Returns
    -------
    MarkerSet
        Face markers named ``upper_01``..., ``lower_01``..., then ``head_01``...

    Raises
    ------
    InputError
        When the candidate sites (those the rig sees) cannot hold the markers asked for; the message gives
        the figures.
    """
    del seed  # the greedy design is deterministic; the argument keeps the interface of the baseline
    if count < 1:
        raise ValueError("count must be >= 1")
    triangles, centroids, regions = face_candidates(basis, rig)
    if rig is not None and not len(triangles):
        raise InputError(f"no site of the face that moves with expression is {rig.describe()}; is the face in "
                         f"front of the cameras?", field="cameras")
    spacing = default_spacing(basis, count, rig) if min_spacing_mm is None else float(min_spacing_mm)
    head = head_markers(basis, n_head, rig)
    # face markers keep the spacing from the head markers too
    head_sites = head.neutral_positions(basis)
    apart = np.all(np.linalg.norm(centroids[:, None] - head_sites[None], axis=2) >= spacing, axis=1)
    triangles, centroids, regions = triangles[apart], centroids[apart], regions[apart]
    displacement = _triangle_displacements(basis)[triangles]  # (n_cand, M, 3)
    thresholds = observer_thresholds(basis)
    alloc = _allocate({r: int(basis.region_mask(r).sum()) for r in REGIONS}, count)
    picked_triangles, picked_regions = [], []
    for region in REGIONS:
        n_region = alloc.get(region, 0)
        in_region = np.flatnonzero(regions == region)
        if n_region == 0:
            continue
        muscles = basis.region_mask(region)
        rows = np.transpose(displacement[in_region][:, muscles], (0, 2, 1))  # (n, 3, m)
        observes = np.linalg.norm(displacement[in_region][:, muscles], axis=2) >= thresholds[muscles]
        ridge = 1e-6 * np.einsum("kdm,kdm->", rows, rows) / max(len(rows), 1)
        chosen = _greedy_design(rows, centroids[in_region], n_region, spacing, ridge)
        if len(chosen) < n_region:
            raise InputError(_shortfall(region, len(chosen), n_region, len(in_region), spacing, rig), field="count")
        chosen = _ensure_observers(rows, observes, centroids[in_region], chosen, spacing, min_observers, ridge)
        chosen = _exchange(rows, observes, centroids[in_region], chosen, spacing, min_observers, ridge)
        order = sorted(chosen, key=lambda c: (-centroids[in_region][c, 1], centroids[in_region][c, 0]))
        picked_triangles += [int(triangles[in_region][c]) for c in order]
        picked_regions += [region] * len(order)
    face = _marker_set(picked_triangles, picked_regions, _face_names(picked_regions), ["face"] * len(picked_regions))
    return _join(face, head)


def _shortfall(region: str, fitted: int, wanted: int, sites: int, spacing: float, rig: RigVisibility | None) -> str:
    """Why a region's markers do not fit, with the figures and what to change."""
    where = f"{sites} candidate sites" + (f" {rig.describe()}" if rig is not None else "")
    change = "fewer markers, a smaller spacing" + (", fewer views, or cameras that see more of the face"
                                                   if rig is not None else "")
    return (f"only {fitted} of the {wanted} {region}-face markers fit {spacing:.1f} mm apart on its {where} "
            f"(and clear of the head markers); ask for {change}")


def farthest_point_markers(basis: Basis, count: int = 64, seed: int = 0, n_head: int = 0) -> MarkerSet:
    """Baseline layout: farthest-point sampling of the same face candidates, from a seeded start.

    Parameters
    ----------
    basis : Basis
    count : int
    seed : int
        Picks the first candidate.
    n_head : int
        Head markers added as in :func:`design_markers`.
    """
    triangles, centroids, regions = face_candidates(basis)
    rng = np.random.default_rng(seed)
    picked = [int(rng.integers(len(triangles)))]
    distance = np.linalg.norm(centroids - centroids[picked[0]], axis=1)
    for _ in range(min(count, len(triangles)) - 1):
        nxt = int(np.argmax(distance))
        picked.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(centroids - centroids[nxt], axis=1))
    picked.sort(key=lambda c: (regions[c] != "upper", -centroids[c, 1], centroids[c, 0]))
    picked_regions = [str(regions[c]) for c in picked]
    face = _marker_set(triangles[picked], picked_regions, _face_names(picked_regions), ["face"] * len(picked))
    return _join(face, head_markers(basis, n_head))


def condition_number(displacement: np.ndarray) -> float:
    """Condition number ``s_max / s_min`` of a displacement matrix, inf when rank deficient.

    Parameters
    ----------
    displacement : ndarray, shape (n_markers, n_muscles, 3)
    """
    n, m, _ = displacement.shape
    if n * 3 < m or m == 0:
        return float("inf")
    singular = np.linalg.svd(np.transpose(displacement, (0, 2, 1)).reshape(3 * n, m), compute_uv=False)
    return float(singular[0] / singular[-1]) if singular[-1] > 1e-12 * max(singular[0], 1e-300) else float("inf")


def _worst_without_one(displacement: np.ndarray) -> float:
    n = len(displacement)
    if n <= 1:
        return float("inf")
    return max(condition_number(np.delete(displacement, k, axis=0)) for k in range(n))


def layout_report(basis: Basis, markers: MarkerSet, rig: RigVisibility | None = None) -> dict:
    """Observability figures of a layout (and, given a rig, how many of its cameras see each marker).

    Returns
    -------
    dict
        ``n_face``, ``n_head``, ``condition_whole`` (all face markers, all muscles),
        ``condition_worst_loss_whole`` (the worst of those with any one face marker removed),
        ``regions``: per region ``{n_markers, n_muscles, condition, condition_worst_loss}`` (its markers,
        its muscles), ``observers``: per muscle the number of its region's markers it moves by at
        least ``max(0.2 x its peak, 0.5 mm)``, ``min_observers``, ``head_spread_mm`` (smallest singular
        value of the centred head-marker positions: > 0 means not coplanar, larger is better spread),
        ``head_motion_mm`` (largest displacement of any head-marker site by any element). With ``rig``:
        ``views``, per marker the number of cameras that see it at the neutral pose as ``rig`` counts (margin
        for head motion included), and ``fewest_views``.
    """
    displacement = markers.displacement_matrix(basis)  # (n, M, 3)
    face = markers.face_mask
    report: dict = {
        "n_face": int(face.sum()), "n_head": int((~face).sum()),
        "condition_whole": condition_number(displacement[face]),
        "condition_worst_loss_whole": _worst_without_one(displacement[face]),
        "regions": {},
    }
    thresholds = observer_thresholds(basis)
    observers = {}
    for region in REGIONS:
        muscles = basis.region_mask(region)
        if not muscles.any():
            continue
        rows = displacement[markers.region_mask(region)][:, muscles]
        report["regions"][region] = {
            "n_markers": int(len(rows)), "n_muscles": int(muscles.sum()),
            "condition": condition_number(rows), "condition_worst_loss": _worst_without_one(rows),
        }
        seen = np.linalg.norm(rows, axis=2) >= thresholds[muscles]
        for name, count in zip(np.array(basis.names)[muscles], seen.sum(axis=0)):
            observers[str(name)] = int(count)
    report["observers"] = {name: observers[name] for name in basis.names if name in observers}
    report["min_observers"] = min(observers.values()) if observers else 0
    head = markers.subset(markers.head_mask)
    if len(head):
        positions = head.neutral_positions(basis)
        report["head_spread_mm"] = float(np.linalg.svd(positions - positions.mean(axis=0), compute_uv=False)[-1])
        moved = np.linalg.norm(head.positions(basis.elements, basis.triangles), axis=2)  # element displacements
        report["head_motion_mm"] = float(moved.max())
    if rig is not None:
        normals = triangle_normals(basis.neutral, basis.triangles[markers.triangles])
        views = rig.seen(basis, markers.neutral_positions(basis), normals).sum(axis=0)
        report["views"] = {name: int(v) for name, v in zip(markers.names, views)}
        report["fewest_views"] = int(views.min()) if len(views) else 0
    return report
