"""Marker reconstruction (correspondence, triangulation, labelling) on a simulated take; DLT vs aniposelib."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

SWAP_MM = 2.0  # a labelled marker farther than this from its true position is an outlier


@dataclass(frozen=True, eq=False)
class SimulatedTake:
    """2D observations of a simulated take with ground truth.

    Attributes
    ----------
    frames_2d : list (n_frames) of list (n_cams) of ndarray, shape (n_detections, 2)
        Undistorted pixel centroids per frame and camera, markers and spurious highlights shuffled.
    t : ndarray, shape (n_frames,)
    points_3d : ndarray, shape (n_frames, n_markers, 3)
        True world positions.
    head2world : ndarray, shape (n_frames, 4, 4)
    displacements : ndarray, shape (n_frames, n_markers, 3)
        True displacements from neutral in the model frame.
    labelled_2d : ndarray, shape (n_frames, n_cams, n_markers, 2)
        The same marker observations by label (distorted pixels, noise included), NaN where unseen.
    """

    frames_2d: list
    t: np.ndarray
    points_3d: np.ndarray
    head2world: np.ndarray
    displacements: np.ndarray
    labelled_2d: np.ndarray


def face_and_markers(count: int = 64, n_head: int = 5):
    """The ICT basis and a marker layout of ``count`` face + ``n_head`` head markers (None without the data).

    The layout is designed for :func:`rig_cameras` (:data:`RIG_MIN_VIEWS` views of every marker at the
    neutral pose, with the layout's margin for head motion), as a face-capture rig's layout is.
    """
    from livebridge.bench.data import ict_basis
    from livebridge.face.layout import design_markers
    from livebridge.face.rig_visibility import RigVisibility

    basis = ict_basis()
    if basis is None:
        return None, None
    # the world frame is the model frame at rest (the performer's head2world starts at identity)
    rig = RigVisibility(rig_cameras(basis), min_views=RIG_MIN_VIEWS, max_view_deg=MAX_VIEW_DEG, model2world=np.eye(4))
    return basis, design_markers(basis, count=count, n_head=n_head, rig=rig)


# Four cameras on the corners of a square around the face's axis: two heights for a vertical baseline,
# two sides for a horizontal one. Every marker must be seen by all four (RIG_MIN_VIEWS): with 10% of views
# occluded, a marker seen by 3 cameras is lost (< 2 views) in 2.8% of frames, one seen by 4 in 0.37%, so
# labelling 99% of all marker-frames needs the layout on the part of the face all four see. Wider
# corners see less of it together (markers closer than ~5 mm: label swaps); narrower ones, or one
# height only, triangulate depth worse.
RIG_AZIMUTH_DEG = 20.0  # cameras at +-20 deg left and right of the face ...
RIG_ELEVATION_DEG = 20.0  # ... and +-20 deg above and below it
RIG_DISTANCE_MM = 700.0
RIG_MIN_VIEWS = 4
MAX_VIEW_DEG = 75.0  # a camera finds a marker whose normal is within this angle of it (simulate hides the rest)


def rig_cameras(basis, distortion: float = -0.08):
    """The simulated face-capture rig: 4 cameras at the corners of a square seen from the face, mild radial ``k1``.

    Cameras at azimuth +-:data:`RIG_AZIMUTH_DEG` and elevation +-:data:`RIG_ELEVATION_DEG`,
    :data:`RIG_DISTANCE_MM` from the face centre and looking at it, the face filling the image height as
    in :func:`livebridge.simulators.rig.generate_cameras`.
    """
    from livebridge.calibration.cameras import CameraGroup
    from livebridge.simulators.rig import face_camera

    corners = [(-1, 1), (1, 1), (-1, -1), (1, -1)]
    cameras = [face_camera(basis, f"cam{k}", np.deg2rad(side * RIG_AZIMUTH_DEG), np.deg2rad(level * RIG_ELEVATION_DEG),
                           RIG_DISTANCE_MM, distortion=np.array([distortion, 0.0, 0.0, 0.0, 0.0]))
               for k, (side, level) in enumerate(corners)]
    return CameraGroup(cameras)


def simulate(basis, markers, cameras, n_frames: int, seed: int = 0, noise_px: float = 0.2, occlusion: float = 0.1,
             spurious: float = 3.0, max_view_deg: float = MAX_VIEW_DEG, head_turn_deg: float = 0.0,
             turn_axis=(0.0, 1.0, 0.0), fps: float = 60.0) -> SimulatedTake:
    """A performer take seen by ``cameras`` at the 2D level (no images).

    Markers facing away from a camera (normal more than ``max_view_deg`` from it) are hidden, then
    a further ``occlusion`` fraction of marker views at random; centroids get Gaussian noise of
    ``noise_px`` per axis; ``spurious`` highlights per camera and frame (Poisson) appear near the
    face; detections are undistorted and shuffled. ``head_turn_deg`` turns the whole performance
    about ``turn_axis`` through the face centre (the first labelling must cope with it).
    """
    from scipy.spatial.transform import Rotation

    from livebridge.face.meshio import triangle_normals
    from livebridge.geometry.transforms import apply
    from livebridge.simulators.performer import perform
    from livebridge.simulators.rig import face_centre

    rng = np.random.default_rng([seed, 61])
    performance = perform(basis, markers, n_frames, fps=fps, seed=seed, script="mixed", head_motion=True)
    turn = np.eye(4)
    if head_turn_deg:
        axis = np.asarray(turn_axis, dtype=np.float64)
        turn[:3, :3] = Rotation.from_rotvec(np.deg2rad(head_turn_deg) * axis / np.linalg.norm(axis)).as_matrix()
        centre = face_centre(basis)
        turn[:3, 3] = centre - turn[:3, :3] @ centre
    head2world = turn @ performance.head2world
    points = apply(turn, performance.marker_positions)
    # marker normals: neutral triangle normals carried by the head pose
    normals = triangle_normals(basis.neutral, basis.triangles[markers.triangles])
    normals_world = np.einsum("fij,nj->fni", head2world[:, :3, :3], normals)
    n_cams, n_markers = len(cameras), len(markers)
    labelled = np.full((n_frames, n_cams, n_markers, 2), np.nan)
    frames_2d = []
    lo = cameras.project(points[0]).reshape(-1, 2)
    box_lo, box_hi = np.nanmin(lo, axis=0), np.nanmax(lo, axis=0)
    for f in range(n_frames):
        pixels = cameras.project(points[f])  # (c, n, 2)
        per_camera = []
        for c, camera in enumerate(cameras.cameras):
            to_camera = camera.center - points[f]
            cosine = (normals_world[f] * to_camera).sum(1) / np.linalg.norm(to_camera, axis=1)
            seen = (cosine > np.cos(np.deg2rad(max_view_deg))) & (rng.random(n_markers) >= occlusion)
            observed = pixels[c] + rng.normal(scale=noise_px, size=pixels[c].shape)
            labelled[f, c, seen] = observed[seen]
            extra = rng.uniform(box_lo, box_hi, size=(rng.poisson(spurious), 2))
            detections = np.concatenate([observed[seen], extra])
            per_camera.append(camera.undistort_points(detections[rng.permutation(len(detections))]))
        frames_2d.append(per_camera)
    return SimulatedTake(frames_2d, performance.t, points, head2world, performance.marker_displacements, labelled)


def evaluate(frames, take: SimulatedTake) -> dict:
    """Accuracy of labelled frames against the truth.

    Returns ``rmse_mm`` (3D error over every labelled marker-frame), ``labelled_fraction`` (of all
    marker-frames), ``labelled_fraction_reconstructible`` (of the marker-frames seen by at least two
    cameras, the ones any reconstruction can label), ``swaps`` (labelled marker-frames whose position
    is nearer another marker's true position than its own: a wrong identity), ``outliers_2mm``
    (labelled marker-frames more than 2 mm from the truth), ``displacement_rmse_mm`` (model frame,
    against the true displacements from neutral) and ``stray_per_frame``.
    """
    world = np.stack([f.positions_world for f in frames])
    seen = np.isfinite(world).all(axis=-1)
    error = np.linalg.norm(world - take.points_3d, axis=-1)
    to_all = np.linalg.norm(world[:, :, None] - take.points_3d[:, None], axis=-1)  # (f, n, n)
    nearest = np.argmin(np.where(np.isfinite(to_all), to_all, np.inf), axis=2)
    swaps = int((seen & (nearest != np.arange(world.shape[1])[None])).sum())
    reconstructible = np.isfinite(take.labelled_2d[..., 0]).sum(axis=1) >= 2
    displacement = np.stack([f.displacements for f in frames])
    disp_error = np.linalg.norm(displacement - take.displacements, axis=-1)
    return {
        "rmse_mm": float(np.sqrt(np.mean(error[seen] ** 2))) if seen.any() else float("nan"),
        "labelled_fraction": float(seen.mean()),
        "labelled_fraction_reconstructible": float((seen & reconstructible).sum() / max(reconstructible.sum(), 1)),
        "swaps": swaps,
        "outliers_2mm": int((seen & (error > SWAP_MM)).sum()),
        "displacement_rmse_mm": float(np.sqrt(np.mean(disp_error[seen] ** 2))) if seen.any() else float("nan"),
        "stray_per_frame": float(np.mean([f.n_stray for f in frames])),
    }


def _aniposelib_group(cameras):
    from aniposelib.cameras import Camera as AnipCamera
    from aniposelib.cameras import CameraGroup as AnipGroup

    return AnipGroup([AnipCamera(matrix=c.matrix, dist=c.distortions, size=c.size, rvec=c.rotation, tvec=c.translation,
                                 name=c.name) for c in cameras.cameras])


def _time_per_call(function, inputs, repeats: int) -> float:
    """Mean over ``inputs`` of each call's best time over ``repeats`` rounds (robust to a busy machine)."""
    best = np.full(len(inputs), np.inf)
    for _ in range(repeats):
        for k, item in enumerate(inputs):
            start = time.perf_counter()
            function(item)
            best[k] = min(best[k], time.perf_counter() - start)
    return float(best.mean())


def triangulation_comparison(cameras, labelled_2d: np.ndarray, n_frames: int, log) -> dict:
    """Our batched DLT vs ``aniposelib.CameraGroup.triangulate`` on the same labelled, undistorted points, per frame.

    Both get the same undistorted observations with the undistortion outside the timing: ours as
    undistorted pixels (it normalises them itself, inside the timing), aniposelib as normalised
    coordinates with ``undistort=False`` (it would otherwise undistort with OpenCV itself).
    """
    from livebridge.reconstruct.triangulate import Triangulator

    triangulator = Triangulator(cameras)
    frames = labelled_2d[:n_frames]
    undistorted = [cameras.undistort_points(f) for f in frames]  # (c, n, 2) each
    normalized = [triangulator.normalize(u) for u in undistorted]
    ours = np.stack([triangulator.dlt(u) for u in undistorted])
    result = {"triangulate_peer": "aniposelib CameraGroup.triangulate (jax DLT), per frame"}
    try:
        group = _aniposelib_group(cameras)
        theirs = np.stack([group.triangulate(n, undistort=False) for n in normalized])
    except Exception as error:  # noqa: BLE001 - the peer may be missing or broken; we report and fall back
        log(f"aniposelib unavailable ({error!r}); comparing with OpenCV triangulatePoints medians")
        return result | _opencv_comparison(triangulator, undistorted, ours)
    both = np.isfinite(ours).all(-1) & np.isfinite(theirs).all(-1)
    result["triangulate_max_diff_mm"] = float(np.abs(ours[both] - theirs[both]).max())
    result["triangulate_same_points"] = bool((np.isfinite(ours).all(-1) == np.isfinite(theirs).all(-1)).all())
    repeats = 5
    ours_s = _time_per_call(triangulator.dlt, undistorted, repeats)
    theirs_s = _time_per_call(lambda n: group.triangulate(n, undistort=False), normalized, repeats)
    result["triangulate_us_per_frame"] = ours_s * 1e6
    result["aniposelib_us_per_frame"] = theirs_s * 1e6
    result["triangulate_speedup_vs_aniposelib"] = theirs_s / ours_s
    # the whole take in one call (aniposelib's best case)
    stacked_u = np.concatenate(undistorted, axis=1)
    stacked_n = np.concatenate(normalized, axis=1)
    group.triangulate(stacked_n, undistort=False)
    ours_b = _time_per_call(triangulator.dlt, [stacked_u], repeats)
    theirs_b = _time_per_call(lambda n: group.triangulate(n, undistort=False), [stacked_n], repeats)
    result["triangulate_batch_speedup_vs_aniposelib"] = theirs_b / ours_b
    return result


def _opencv_comparison(triangulator, undistorted, ours) -> dict:
    import itertools

    import cv2

    def opencv(points):
        estimates = []
        for a, b in itertools.combinations(range(len(points)), 2):
            pa, pb = triangulator.normalize(points[a:a + 1])[0], triangulator.normalize(points[b:b + 1])[0]
            x = cv2.triangulatePoints(triangulator.extrinsics[a], triangulator.extrinsics[b], pa.T, pb.T)
            estimates.append((x[:3] / x[3]).T)
        return np.nanmedian(np.stack(estimates), axis=0)

    theirs = np.stack([opencv(u) for u in undistorted])
    both = np.isfinite(ours).all(-1) & np.isfinite(theirs).all(-1)
    ours_s = _time_per_call(triangulator.dlt, undistorted, 3)
    theirs_s = _time_per_call(opencv, undistorted, 3)
    return {"triangulate_peer": "OpenCV triangulatePoints pairwise medians (aniposelib could not run)",
            "triangulate_max_diff_mm": float(np.abs(ours[both] - theirs[both]).max()),
            "triangulate_speedup_vs_aniposelib": theirs_s / ours_s, "triangulate_us_per_frame": ours_s * 1e6}


def _opencv_detect_blobs(image: np.ndarray, config) -> np.ndarray:
    """The job of ``detect_blobs`` as a user would write it with OpenCV: the detection benchmark's peer.

    The same threshold statistics (numpy medians), ``cv2.threshold``, ``cv2.connectedComponentsWithStats``,
    then for each blob of accepted area its window (bounding box grown by the margin) with the border
    median subtracted and other blobs' pixels masked, and ``cv2.moments`` for the intensity-weighted
    centroid and the second moments of the circularity filter.

    Parameters
    ----------
    image : ndarray of uint8, shape (height, width)
    config : DetectConfig

    Returns
    -------
    ndarray, shape (n_blobs, 2)
        Pixel coordinates ``(x, y)``.
    """
    import cv2

    sample = image[::4, ::4]
    background = float(np.median(sample))
    noise = 1.4826 * float(np.median(np.abs(sample - background)))
    level = max(background + config.contrast * (float(image.max()) - background), background + 6 * noise)
    mask = cv2.threshold(image, level, 255, cv2.THRESH_BINARY)[1]
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    height, width = image.shape
    m = config.margin
    found = []
    for label in range(1, count):
        x, y, w, h, area = stats[label]
        if not config.min_area <= area <= config.max_area:
            continue
        xa, ya, xb, yb = max(x - m, 0), max(y - m, 0), min(x + w + m, width), min(y + h + m, height)
        patch = image[ya:yb, xa:xb].astype(np.float32)
        border = np.concatenate([patch[0], patch[-1], patch[1:-1, 0], patch[1:-1, -1]])
        weight = np.maximum(patch - np.median(border), 0)
        own = labels[ya:yb, xa:xb]
        weight[(own != 0) & (own != label)] = 0
        moments = cv2.moments(weight)
        total = moments["m00"]
        if total <= 0:
            continue
        cxx, cyy, cxy = moments["mu20"] / total, moments["mu02"] / total, moments["mu11"] / total
        spread = np.hypot((cxx - cyy) / 2, cxy)
        major, minor = (cxx + cyy) / 2 + spread, (cxx + cyy) / 2 - spread
        if major > 0 and np.sqrt(max(minor, 0.0) / major) >= config.min_circularity:
            found.append((xa + moments["m10"] / total, ya + moments["m01"] / total))
    return np.array(found).reshape(-1, 2)


def _centroid_accuracy(detect, images, truths) -> tuple[float, float]:
    """Centroid error of a detector on rendered frame sets against the rig's truth.

    Parameters
    ----------
    detect : callable
        ``detect(image (height, width)) -> (n_blobs, 2)``.
    images : list (n_frames) of list (n_cams) of ndarray
    truths : list (n_frames) of rig truth (``points_2d (n_cams, n_markers, 2)``, ``visible (n_cams, n_markers)``)

    Returns
    -------
    rms_px : float
        RMS distance of each visible marker to its nearest blob, over those within 1.5 px (NaN if none).
    found_fraction : float
        Visible markers with a blob within 1.5 px.
    """
    errors, found, expected = [], 0, 0
    for frameset, truth in zip(images, truths):
        for c, image in enumerate(frameset):
            blobs = detect(image)
            true = truth.points_2d[c][truth.visible[c]]
            expected += len(true)
            if len(blobs) and len(true):
                distance = np.linalg.norm(blobs[:, None] - true[None], axis=-1).min(axis=0)
                hit = distance < 1.5
                found += int(hit.sum())
                errors.append(distance[hit])
    errors = np.concatenate(errors) if errors else np.zeros(0)
    return float(np.sqrt(np.mean(errors**2))) if len(errors) else float("nan"), found / max(expected, 1)


def detection_timing(basis, markers, n_frames: int, seed: int = 0) -> dict:
    """Detection on the simulated rig's rendered images, ours vs a plain OpenCV pipeline doing the same job.

    Both run on the same images with the default :class:`DetectConfig`: ms per image (each image's best
    of 3 rounds) and centroid error vs the rig's truth (px).
    """
    from livebridge.reconstruct.detect import DetectConfig, detect_blobs
    from livebridge.simulators.rig import RigConfig, SimRig

    rig = SimRig(basis, markers, config=RigConfig(spurious_rate=2.0), seed=seed)
    images, truths = [], []
    for frameset in rig.framesets(n_frames):
        images.append([frame.image for frame in frameset.frames])
        truths.append(frameset.truth)
    flat = [image for frameset in images for image in frameset]
    config = DetectConfig()

    def opencv(image):
        return _opencv_detect_blobs(image, config)

    detect_blobs(flat[0])  # the compiled code is loaded (or, on a fresh install, compiled) on first use
    ours_s, opencv_s = _time_per_call(detect_blobs, flat, 3), _time_per_call(opencv, flat, 3)
    ours_rms, found = _centroid_accuracy(detect_blobs, images, truths)
    opencv_rms, opencv_found = _centroid_accuracy(opencv, images, truths)
    return {"detect_ms_per_image": ours_s * 1e3,
            "detect_centroid_rms_px": ours_rms,
            "detect_found_fraction": found,
            "detect_peer": "OpenCV: threshold, connectedComponentsWithStats, moments of each blob's window",
            "detect_opencv_ms_per_image": opencv_s * 1e3,
            "detect_speedup_vs_opencv": opencv_s / ours_s,
            "detect_opencv_centroid_rms_px": opencv_rms,
            "detect_opencv_found_fraction": opencv_found}


def run(quick: bool, log) -> dict:
    from livebridge.reconstruct.pipeline import Reconstructor

    n_frames = 300 if quick else 3000
    basis, markers = face_and_markers()
    if basis is None:
        raise RuntimeError("the reference data (../shared/data) is needed for this benchmark")
    cameras = rig_cameras(basis)
    log(f"simulating {n_frames} frames: {len(cameras)} cameras (azimuth +-{RIG_AZIMUTH_DEG:g} deg, elevation "
        f"+-{RIG_ELEVATION_DEG:g} deg), {int(markers.face_mask.sum())} face + "
        f"{int(markers.head_mask.sum())} head markers, 0.2 px noise, 10% occlusion, spurious highlights")
    take = simulate(basis, markers, cameras, n_frames, seed=1)
    reconstructor = Reconstructor(cameras, markers, basis)
    start = time.perf_counter()
    frames = reconstructor.run(take.frames_2d, take.t)
    seconds = time.perf_counter() - start
    result = {"frames": n_frames, "cameras": len(cameras), "markers": len(markers),
              "ms_per_frame": seconds / n_frames * 1e3}
    result |= evaluate(frames, take)
    log("timing triangulation against aniposelib")
    result |= triangulation_comparison(cameras, take.labelled_2d, min(n_frames, 300), log)
    log("timing detection on rendered images")
    result |= detection_timing(basis, markers, 5 if quick else 20)
    result["pass"] = bool(result["triangulate_speedup_vs_aniposelib"] >= 20 and result["rmse_mm"] <= 0.2
                          and result["swaps"] == 0
                          and result["labelled_fraction"] >= 0.99
                          and result.get("triangulate_max_diff_mm", 0.0) <= 1e-6)
    return result


