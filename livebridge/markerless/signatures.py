"""Signature bases of a co-articulation region: ICA (the paper's) or PCA, and the back-substitution matrix.

A CR's training samples ``S (n_pixels, n_samples)`` (one column per masked, scanned gesture frame) are
modelled as ``S = B A`` with a basis ``B (n_pixels, k)`` of statistically independent images (spatial ICA,
FastICA on the pixels as observations). A new sample ``x`` goes to signature space by least squares,
``c = argmin |B c - x|``, computed as one matrix product with the SVD back-substitution matrix
``M = V D^-1 U^T`` (``B = U D V^T``); its signature is ``sigma = c / |c|``. The PCA variant uses the leading
left singular vectors of the samples (each less its mean over the pixels, as FastICA centres them) as ``B``
and is otherwise identical.
"""

from __future__ import annotations

import numpy as np

METHODS = ("ica", "pca")
_RELATIVE_RANK_TOL = 1e-6


def require_sklearn():
    """scikit-learn's FastICA, or an ImportError naming the extra to install."""
    try:
        from sklearn.decomposition import FastICA
    except ImportError as error:  # the optional extra is missing
        raise ImportError("markerless training with ICA needs scikit-learn: "
                          "pip install 'livebridge[markerless]'") from error
    return FastICA


def signature_basis(samples: np.ndarray, n_components: int, method: str = "ica", seed: int = 0) -> np.ndarray:
    """A signature basis for one CR.

    Parameters
    ----------
    samples : ndarray, shape (n_pixels, n_samples)
        Training samples as columns.
    n_components : int
        Wanted basis size; capped at the samples' numerical rank.
    method : {"ica", "pca"}
    seed : int
        FastICA's initial unmixing matrix.

    Returns
    -------
    ndarray, shape (n_pixels, k), float64
        Basis images as columns, ``k <= n_components``.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    samples = np.asarray(samples, dtype=np.float64)
    # as FastICA does with pixels as observations: each sample loses its mean over the pixels (its DC); the
    # mean image stays in the basis, so no trained appearance projects to c = 0
    centred = samples - samples.mean(axis=0, keepdims=True)
    # the samples' principal directions from their small Gram matrix (n_samples^2, not a pixel-sized SVD)
    eigenvalues, vectors = np.linalg.eigh(centred.T @ centred)
    order = np.argsort(eigenvalues)[::-1]
    singular = np.sqrt(np.clip(eigenvalues[order], 0.0, None))
    rank = int(np.sum(singular > _RELATIVE_RANK_TOL * max(singular[0], 1e-300))) if len(singular) else 0
    k = max(1, min(int(n_components), rank))
    principal = centred @ vectors[:, order[:k]]  # (n_pixels, k): u * s, principal images times their singular values
    if method == "pca" or rank == 0:  # samples all alike (a region no gesture changed): nothing to unmix
        return principal
    fast_ica = require_sklearn()
    # pixels are the observations: the columns of B (images) are the independent, non-Gaussian sources. They
    # are whitened here (the principal images are orthogonal: each over its RMS) and FastICA only rotates them:
    # its own whitening of these orthogonal columns (whiten_solver="eigh", scikit-learn 1.7-1.9) collapsed
    # every source onto one image in the bench's eye-and-brow regions, so that those regions read neutral
    # whatever the face did (bench state accuracy 0.76; 0.91 whitened here)
    white = principal / (singular[:k] / np.sqrt(len(principal)))
    ica = fast_ica(whiten=False, max_iter=100, tol=1e-3, random_state=seed)
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    with warnings.catch_warnings():
        # the unmixing is a rotation of the whitened principal subspace, and signatures compare directions in
        # it: a run stopped early spans the same subspace and classifies the same
        warnings.simplefilter("ignore", ConvergenceWarning)
        return ica.fit_transform(white)


def back_substitution(basis: np.ndarray) -> np.ndarray:
    """The least-squares back-substitution matrix ``M = V D^-1 U^T`` of ``B = U D V^T``.

    Parameters
    ----------
    basis : ndarray, shape (n_pixels, k)

    Returns
    -------
    ndarray, shape (k, n_pixels)
        ``M @ x`` is the least-squares ``c`` of ``B c = x``; singular values below a relative tolerance are
        dropped (their ``1/d`` is taken as 0), as in a pseudo-inverse.
    """
    u, d, vt = np.linalg.svd(np.asarray(basis, dtype=np.float64), full_matrices=False)
    keep = d > _RELATIVE_RANK_TOL * max(d[0], 1e-300) if len(d) else d > 0
    inverse = np.zeros_like(d)
    inverse[keep] = 1.0 / d[keep]
    return (vt.T * inverse) @ u.T


def signatures(back: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Unit signatures ``sigma = c / |c|`` of samples, ``c = M x``.

    Parameters
    ----------
    back : ndarray, shape (k, n_pixels)
        Back-substitution matrix.
    samples : ndarray, shape (n_pixels, n_samples)

    Returns
    -------
    ndarray, shape (n_samples, k)
        One unit row per sample (a zero row for a sample with ``c = 0``).
    """
    coords = (back @ samples).T
    return unit_rows(coords)


def unit_rows(rows: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length, shape as given; zero rows stay zero."""
    norm = np.linalg.norm(rows, axis=-1, keepdims=True)
    return np.divide(rows, norm, out=np.zeros_like(rows), where=norm > 0)
