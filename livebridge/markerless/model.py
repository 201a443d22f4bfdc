"""The trained markerless model: co-articulation regions, their signature sets, and how images are normalised.

Saved as one ``.npz`` (no pickles): a JSON manifest (names, sizes, settings) and named arrays. The
per-(gesture, state) canonical frames are stored as 8-bit crops around the regions the gesture acts on;
:meth:`MarkerlessModel.state_frame` pastes one over the neutral image.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.markerless.normalise import HeadRig, Normalisation
from livebridge.npzio import read_npz

FORMAT = "livebridge-markerless"
VERSION = 1


@dataclass(frozen=True, eq=False)
class RegionModel:
    """One co-articulation region.

    Attributes
    ----------
    name : str
    mask : ndarray, shape (H, W), bool
        In the canonical image (size ``MarkerlessModel.image_size``).
    muscles : tuple of str
        The muscles and pseudo-muscles (e.g. ``"frontalis_L+corrugator_L"``) classified in this CR.
    n_states : tuple of int
        Per muscle, the signature-set size ``|Phi_i|`` (state 0 = neutral).
    back : ndarray, shape (k, n_pixels), float32
        The back-substitution matrix ``M = V D^-1 U^T`` over the mask's pixels (row-major order).
    signatures : tuple of ndarray, each shape (n_states_i, k)
        ``Phi_i``: unit signatures of muscle i's states, neutral to full.
    actuations : ndarray, shape (n_region_muscles, n_basis_muscles)
        What full actuation of each (pseudo-)muscle means in basis contractions.
    weights : ndarray, shape (n_basis_muscles,)
        For each basis muscle this CR reports, the share of the muscle's region of influence inside the CR
        (0: not reported); a muscle's contraction is the weighted mean of its CRs' values.
    sample_norm : float
        Median norm of the training samples (a sample far from it is not a trained face).
    """

    name: str
    mask: np.ndarray
    muscles: tuple[str, ...]
    n_states: tuple[int, ...]
    back: np.ndarray
    signatures: tuple[np.ndarray, ...]
    actuations: np.ndarray
    weights: np.ndarray
    sample_norm: float

    @cached_property
    def pixels(self) -> np.ndarray:
        """Flat indices of the mask's pixels, shape (n_pixels,)."""
        return np.flatnonzero(self.mask)


class MarkerlessModel:
    """A trained CoArt model.

    Parameters
    ----------
    muscle_names : tuple of str
        The basis muscles (contraction vector order).
    regions : tuple of RegionModel
    normalisation : Normalisation
    neutral_image : ndarray, shape (H, W), float32
        Canonical neutral image (before lighting normalisation).
    gestures : dict of str -> (ndarray (n_states - 1, h, w) uint8, (x, y, w, h))
        Per trained (pseudo-)muscle, the canonical frames of states 1.. and the box they cover.
    method : {"ica", "pca"}
    """

    def __init__(self, muscle_names, regions, normalisation: Normalisation, neutral_image: np.ndarray,
                 gestures: dict, method: str = "ica"):
        self.muscle_names = tuple(muscle_names)
        self.regions = tuple(regions)
        self.normalisation = normalisation
        self.neutral_image = np.asarray(neutral_image, dtype=np.float32)
        self.gestures = dict(gestures)
        self.method = method

    @property
    def image_size(self) -> tuple[int, int]:
        """Canonical image ``(W, H)``."""
        return self.normalisation.image_size

    @property
    def n_muscles(self) -> int:
        return len(self.muscle_names)

    def region(self, name: str) -> RegionModel:
        for region in self.regions:
            if region.name == name:
                return region
        raise KeyError(f"no region {name!r}; the model has {[r.name for r in self.regions]}")

    def state_frame(self, region: str, muscle: str, state: int) -> np.ndarray:
        """The canonical frame that defines ``state`` of ``muscle`` in ``region``, shape (H, W) float32."""
        cr = self.region(region)
        if muscle not in cr.muscles:
            raise KeyError(f"region {region!r} has no muscle {muscle!r} (it has {cr.muscles})")
        n_states = cr.n_states[cr.muscles.index(muscle)]
        if not 0 <= state < n_states:
            raise IndexError(f"state {state} out of 0..{n_states - 1}")
        frame = self.neutral_image.copy()
        if state > 0:
            crops, (x, y, w, h) = self.gestures[muscle]
            frame[y:y + h, x:x + w] = crops[state - 1]
        return frame

    def save(self, path: str | Path) -> None:
        """Write the model as ``.npz`` (compressed, atomically)."""
        from livebridge.atomic import write_bytes_atomically

        arrays, manifest = _to_arrays(self)
        import io

        buffer = io.BytesIO()
        np.savez_compressed(buffer, manifest=np.array(json.dumps(manifest)), **arrays)
        write_bytes_atomically(path, buffer.getvalue(), "markerless model")

    @classmethod
    def load(cls, path: str | Path) -> MarkerlessModel:
        """Read a model written by :meth:`save`; anything malformed raises :class:`InputError`."""
        return _from_arrays(path)


def _to_arrays(model: MarkerlessModel) -> tuple[dict[str, np.ndarray], dict]:
    norm = model.normalisation
    arrays = {"neutral_image": model.neutral_image, "camera_matrix": norm.camera_matrix,
              "distortions": norm.distortions}
    if norm.canonical_head2cam is not None:
        arrays["canonical_head2cam"] = norm.canonical_head2cam
    if norm.surface is not None:
        arrays["surface"] = norm.surface
    if norm.head_rig is not None:
        arrays["rig_leds"] = norm.head_rig.leds
        arrays["rig_face_point"] = norm.head_rig.face_point
        arrays["rig_face_normal"] = norm.head_rig.face_normal
    regions = []
    for j, region in enumerate(model.regions):
        arrays[f"region{j}_mask"] = region.mask
        arrays[f"region{j}_back"] = region.back
        arrays[f"region{j}_actuations"] = region.actuations
        arrays[f"region{j}_weights"] = region.weights
        for i, signature in enumerate(region.signatures):
            arrays[f"region{j}_phi{i}"] = signature
        regions.append({"name": region.name, "muscles": list(region.muscles), "n_states": list(region.n_states),
                        "sample_norm": region.sample_norm})
    gestures = []
    for g, (name, (crops, box)) in enumerate(model.gestures.items()):
        arrays[f"gesture{g}_frames"] = crops
        gestures.append({"name": name, "box": [int(v) for v in box]})
    manifest = {"format": FORMAT, "version": VERSION, "muscle_names": list(model.muscle_names),
                "method": model.method, "regions": regions, "gestures": gestures,
                "normalisation": {"input_size": list(norm.input_size), "crop": list(norm.crop),
                                  "pose_warp": norm.pose_warp, "laplacian": norm.laplacian, "log": norm.log,
                                  "blur_sigma": norm.blur_sigma, "clip": norm.clip}}
    return arrays, manifest


def _from_arrays(path: str | Path) -> MarkerlessModel:
    path = Path(path)
    arrays = read_npz(path, "markerless model")
    reader = _Reader(path, arrays)
    manifest = reader.manifest()
    settings = manifest["normalisation"]
    rig = None
    if "rig_leds" in arrays:
        rig = HeadRig(reader.array("rig_leds", (4, 3)), reader.array("rig_face_point", (3,)),
                      reader.array("rig_face_normal", (3,)))
    try:
        norm = Normalisation(tuple(settings["input_size"]), rig, reader.array("camera_matrix", (3, 3)),
                             reader.array("distortions", None),
                             reader.array("canonical_head2cam", (4, 4)) if "canonical_head2cam" in arrays else None,
                             tuple(settings["crop"]), None, bool(settings["pose_warp"]), bool(settings["laplacian"]),
                             bool(settings["log"]), float(settings["blur_sigma"]))
        clip = settings.get("clip")
        if clip is not None:
            norm = replace(norm, clip=float(clip))
        if "surface" in arrays:
            width, height = norm.input_size
            norm = replace(norm, surface=reader.array("surface", (height, width, 3)).astype(np.float32))
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(f"bad normalisation settings ({error})", path, "manifest.normalisation") from None
    width, height = norm.image_size
    neutral = reader.array("neutral_image", (height, width))
    muscle_names = tuple(str(n) for n in manifest["muscle_names"])
    regions = tuple(reader.region(j, entry, (height, width), len(muscle_names))
                    for j, entry in enumerate(manifest["regions"]))
    gestures = {}
    for g, entry in enumerate(manifest["gestures"]):
        x, y, w, h = (int(v) for v in entry["box"])
        if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > width or y + h > height:
            raise InputError(f"box {entry['box']} outside the image", path, f"gestures[{g}].box")
        gestures[str(entry["name"])] = (reader.array(f"gesture{g}_frames", (None, h, w)), (x, y, w, h))
    for region in regions:
        for muscle, n_states in zip(region.muscles, region.n_states):
            if muscle not in gestures or len(gestures[muscle][0]) != n_states - 1:
                raise InputError(f"muscle {muscle!r} of region {region.name!r} has no frames for its "
                                 f"{n_states} states", path, "gestures")
    return MarkerlessModel(muscle_names, regions, norm, neutral, gestures, str(manifest["method"]))


class _Reader:
    """Checked access to the arrays of a model file (errors name the file and the array)."""

    def __init__(self, path: Path, arrays: dict[str, np.ndarray]):
        self.path, self.arrays = path, arrays

    def manifest(self) -> dict:
        try:
            manifest = json.loads(str(self.arrays["manifest"]))
        except KeyError:
            raise InputError("no manifest: not a markerless model", self.path, "manifest") from None
        except json.JSONDecodeError as error:
            raise InputError(f"manifest is not JSON ({error})", self.path, "manifest") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            raise InputError(f"not a markerless model (format {FORMAT!r} expected)", self.path, "manifest.format")
        if manifest.get("version") != VERSION:
            raise InputError(f"version {manifest.get('version')!r} not supported (this livebridge reads "
                             f"{VERSION})", self.path, "manifest.version")
        for key, kind in (("muscle_names", list), ("regions", list), ("gestures", list),
                          ("normalisation", dict), ("method", str)):
            if not isinstance(manifest.get(key), kind):
                raise InputError(f"expected {kind.__name__}", self.path, f"manifest.{key}")
        if not manifest["regions"]:
            raise InputError("no regions: a model without them reads nothing from a face", self.path,
                             "manifest.regions")
        return manifest

    def array(self, key: str, shape: tuple | None) -> np.ndarray:
        if key not in self.arrays:
            raise InputError("missing", self.path, key)
        array = self.arrays[key]
        if shape is not None and (array.ndim != len(shape)
                                  or any(s is not None and s != a for s, a in zip(shape, array.shape))):
            raise InputError(f"shape {array.shape}, expected {shape}", self.path, key)
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise InputError("holds non-finite values", self.path, key)
        return array

    def region(self, j: int, entry: dict, size: tuple[int, int], n_basis: int) -> RegionModel:
        field = f"regions[{j}]"
        try:
            name, muscles = str(entry["name"]), tuple(str(m) for m in entry["muscles"])
            n_states = tuple(int(n) for n in entry["n_states"])
            sample_norm = float(entry["sample_norm"])
        except (KeyError, TypeError, ValueError) as error:
            raise InputError(f"malformed ({error})", self.path, field) from None
        if len(n_states) != len(muscles) or min(n_states, default=0) < 1:
            raise InputError("n_states must give one count >= 1 per muscle", self.path, f"{field}.n_states")
        mask = self.array(f"region{j}_mask", size).astype(bool)
        back = self.array(f"region{j}_back", (None, int(mask.sum()))).astype(np.float32)
        k = back.shape[0]
        signatures = tuple(self.array(f"region{j}_phi{i}", (n, k)).astype(np.float32)
                           for i, n in enumerate(n_states))
        actuations = self.array(f"region{j}_actuations", (len(muscles), n_basis))
        weights = self.array(f"region{j}_weights", (n_basis,))
        if (weights < 0).any():
            raise InputError("weights must not be negative", self.path, f"region{j}_weights")
        return RegionModel(name, mask, muscles, n_states, back, signatures, actuations, weights, sample_norm)
