"""Camera nodes: cameras on other PCs that detect their markers there and stream the centroids over ZeroMQ.

A node (:mod:`livebridge.nodes.node`, ``livebridge node``) opens its local cameras, runs the same blob
detector as the host (:func:`livebridge.reconstruct.detect.detect_blobs`) and publishes per frame the
centroids, capture time, frame number and camera id (:mod:`livebridge.nodes.protocol`, msgpack). On the
host one ``node://HOST:PORT?camera=ID`` source per remote camera (:mod:`livebridge.nodes.source`) delivers
those frames with their centroids attached, in host time (:mod:`livebridge.nodes.clock`), so
synchronisation, reconstruction, solve and outputs are the ones of local cameras.

Needs the optional ``nodes`` extra (``pip install "livebridge[nodes]"``: pyzmq and msgpack); imported only
here, and :func:`require` names the extra when it is missing.
"""

from __future__ import annotations

from livebridge.errors import InputError


def require():
    """``(zmq, msgpack)``, or an :class:`InputError` naming the extra that provides them."""
    try:
        import msgpack
        import zmq
    except ImportError as error:
        raise InputError(f"camera nodes need the 'nodes' extra: pip install \"livebridge[nodes]\" ({error.name} "
                         "is not installed)") from None
    return zmq, msgpack
