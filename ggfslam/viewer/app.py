"""``ggfslam view``: a viser server showing a finished (or stopped) run folder."""
from __future__ import annotations

import contextlib
import errno
import io
import socket
from pathlib import Path

from ggfslam.errors import ViewerError

DEFAULT_HOST = "127.0.0.1"  # localhost only: reach it from elsewhere through SSH port forwarding, or pass --host
DEFAULT_PORT = 8080


def check_port(host: str, port: int) -> None:
    """Fail with one line when ``host:port`` cannot be bound (viser itself would silently move to the next port)."""
    if port == 0:
        return  # the system picks a free one
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise ViewerError(f"port {port} on {host} is taken (another viewer?); choose another with --port") \
                    from None
            raise ViewerError(f"cannot listen on {host}:{port}: {e.strerror}") from None


def start_server(host: str, port: int):
    """A viser server on ``host:port`` (checked first); returns it."""
    check_port(host, port)
    try:
        import viser
    except ImportError:
        raise ViewerError("the viewer needs viser: pip install 'viser>=1.1,<2'") from None
    with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: we print one address line
        return viser.ViserServer(host=host, port=port, verbose=False)


def viewer_address(port: int, host: str) -> str:
    """The address to open, with the SSH forwarding hint for a localhost-bound server."""
    shown = "localhost" if host in ("127.0.0.1", "localhost", "::1") else host
    url = f"http://{shown}:{port}"
    if shown == "localhost":
        url += f"  (from another machine: ssh -L {port}:localhost:{port} THIS_HOST, then open that address)"
    return url


def serve_run(run_dir: str | Path, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
              max_splats: int = 1_000_000):
    """Start the viewer of a run folder; returns (server, scene). The server runs in background threads."""
    from ggfslam.viewer.frames import FrameViews
    from ggfslam.viewer.layers import load_run_layers
    from ggfslam.viewer.scene import RunScene

    check_port(host, port)  # before the layers load: a taken port fails in a blink
    layers = load_run_layers(run_dir, max_splats)
    server = start_server(host, port)
    t = layers.trajectories
    frames = FrameViews(layers.run_dir, t.stamps, t.est) if t is not None else None
    scene = RunScene(server, layers, frames, title=f"ggfslam: {layers.run_dir.name}")
    scene.draw_all()
    return server, scene
