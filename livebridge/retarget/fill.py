"""A whole basis from a few scans: the muscles no expression scan shows, retargeted from a template basis.

A person scanned in a few expressions (a brow raise, a smile, the jaw) gets those elements measured
(:mod:`~livebridge.retarget.scans`); an animatronic head or a marker solve needs every muscle of its basis. The
others come from a template basis (the built-in face, ICT's, another person's) carried onto the scanned neutral
by the landmark transfer of :mod:`~livebridge.retarget.basis`, as ``livebridge retarget basis`` would: a
retargeted element moves the scanned face the way the template's face moves, not the way this person's does, so
the build says which elements were measured and which were filled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.retarget.landmarks import LandmarkSet


@dataclass(frozen=True)
class FilledBasis:
    """A scanned basis completed from a template.

    Attributes
    ----------
    basis : Basis
        The template's muscles in its order (each scanned one's own element and muscle), then any scanned muscle
        the template lacks.
    filled : tuple of str
        The muscles retargeted from the template.
    """

    basis: Basis
    filled: tuple[str, ...]


def fill_basis(scanned: Basis, scanned_landmarks: LandmarkSet, template: Basis, template_landmarks: LandmarkSet,
               kernel: str = "r", template_source=None) -> FilledBasis:
    """``scanned`` (the elements the scans built, on their neutral grid) with every muscle of ``template`` it
    lacks retargeted onto its neutral.

    Parameters
    ----------
    scanned : Basis
    scanned_landmarks : LandmarkSet
        On the scanned basis's neutral (``FaceScan.landmark_set``); must name every landmark of
        ``template_landmarks``.
    template : Basis
    template_landmarks : LandmarkSet
        On the template's neutral.
    kernel : str
        The transfer's TPS kernel.
    template_source : str or Path, optional
        The template's landmark file, named in errors.
    """
    from livebridge.retarget.basis import retarget_basis
    from livebridge.retarget.checks import check_landmarks_on

    missing = [muscle for muscle in template.muscles if muscle.name not in scanned.names]
    if not missing:
        return FilledBasis(scanned, ())
    lacking = [name for name in template_landmarks.names if name not in scanned_landmarks.names]
    if lacking:
        raise InputError(f"the scanned neutral's landmarks lack {', '.join(lacking)}, which the template's name: "
                         "give them in the neutral's landmark file, or template landmarks without them",
                         template_source, lacking[0])
    check_landmarks_on(template_landmarks, template.neutral, template.triangles, template_source)
    part = Basis(template.neutral, template.triangles, template.elements[[template.index(m.name) for m in missing]],
                 tuple(missing))
    carried = retarget_basis(part, template_landmarks, scanned.neutral, scanned.triangles,
                             scanned_landmarks, kernel)
    elements, muscles = [], []
    for muscle in template.muscles:
        from_scans = muscle.name in scanned.names
        source = scanned if from_scans else carried
        elements.append(source.elements[source.index(muscle.name)])
        muscles.append(source.muscles[source.index(muscle.name)])
    for muscle in scanned.muscles:
        if muscle.name not in template.names:
            elements.append(scanned.elements[scanned.index(muscle.name)])
            muscles.append(muscle)
    return FilledBasis(Basis(scanned.neutral, scanned.triangles, np.stack(elements), tuple(muscles)),
                       tuple(muscle.name for muscle in missing))
