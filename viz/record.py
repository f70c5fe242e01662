"""Rerun recordings of a fit: reference, measured-parameter and fitted-parameter behaviour.

rerun-sdk is imported here only, so simulation and fitting run without it (the GPU machine,
minimal installs). A recording is written to a temporary file that is renamed into place on close,
so a killed run never leaves a recording that looks complete.

Importing rerun-sdk takes about a second, as long as a whole PD fit. So a command that records starts a
writer process first (`start_writer`), which imports rerun on the other core while this process fits; a
`Recorder` then keeps its calls and hands them to the writer on close. Without a writer (or if it fails) the
calls are replayed here: the same recording either way.
"""
from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np

COLORS = {
    "reference": (230, 230, 230),
    "measured": (230, 120, 40),
    "fitted": (40, 160, 230),
    "analytic": (80, 200, 80),
    "tolerance": (150, 150, 150),
}


def rerun_available() -> bool:
    """Whether rerun-sdk is installed, without importing it (a second)."""
    import importlib.util

    return importlib.util.find_spec("rerun") is not None


def _role(path: str) -> str | None:
    """reference / measured / fitted / analytic: from the entity path's first part, else its last."""
    parts = path.strip("/").split("/")
    return next((p for p in (parts[0], parts[-1]) if p in COLORS), None)


def _color_for(path: str):
    role = _role(path)
    return None if role is None else COLORS[role]


def _side_eye(points) -> tuple[list[float], list[float]]:
    """Camera position and target that frame `points` from the side (-y), a little above."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    lo, hi = p.min(axis=0), p.max(axis=0)
    centre, extent = 0.5 * (lo + hi), max(float(np.max(hi - lo)), 1e-3)
    return (centre + np.array([0.0, -1.25 * extent, 0.1 * extent])).tolist(), centre.tolist()


# timelines counted in integers; every other timeline is a duration in seconds
SEQUENCE_TIMELINES = ("generation", "resolution", "segments", "bodies", "trial", "cell")


class LiveRecorder:
    """Thin wrapper over a rerun RecordingStream saving to `path` (atomically, on close)."""

    def __init__(self, path: str | os.PathLike, application_id: str = "wrenorm", recording_id: str | None = None):
        import rerun as rr

        self._rr = rr
        self.path = Path(path)
        self._tmp = self.path.with_name(self.path.name + ".partial")
        self.stream = rr.RecordingStream(application_id, recording_id=recording_id)
        self.stream.save(str(self._tmp))
        self._views: list[tuple] = []
        self._styled: set[str] = set()
        self._timeline: str | None = None

    def show_timeline(self, name: str) -> None:
        """The timeline the viewer opens on (e.g. sim_time for motion, not the search's generations)."""
        self._timeline = name

    # --- layout ----------------------------------------------------------------
    def add_view(self, name: str, contents: list[str], kind: str = "timeseries", around=None) -> None:
        """Declare a view (kind: timeseries | spatial3d | spatial2d | text) so that related entities
        (reference, measured, fitted of one condition) share one plot instead of the viewer's
        automatic one-entity-per-plot layout. around (spatial3d): points (..., 3) the camera frames,
        seen from the side (-y), z up."""
        self._views.append((kind, name, contents, None if around is None else _side_eye(around)))

    def _send_blueprint(self) -> None:
        if not self._views:
            return
        import rerun.blueprint as rrb

        make = {"timeseries": rrb.TimeSeriesView, "spatial3d": rrb.Spatial3DView,
                "spatial2d": rrb.Spatial2DView, "text": rrb.TextDocumentView}
        views = []
        for kind, name, contents, eye in self._views:
            extra = {} if eye is None else {"eye_controls": rrb.EyeControls3D(position=eye[0], look_target=eye[1],
                                                                               eye_up=(0.0, 0.0, 1.0))}
            views.append(make[kind](name=name, origin="/", contents=contents, **extra))
        panels = [rrb.TimePanel(timeline=self._timeline, state="collapsed")] if self._timeline else []
        self.stream.send_blueprint(rrb.Blueprint(rrb.Grid(*views), *panels, collapse_panels=True))

    # --- time ----------------------------------------------------------------
    def _at(self, t: float | None, timeline: str):
        if t is None:
            self.stream.disable_timeline(timeline) if hasattr(self.stream, "disable_timeline") else None
        elif timeline in SEQUENCE_TIMELINES:
            self.stream.set_time(timeline, sequence=int(t))
        else:
            self.stream.set_time(timeline, duration=float(t))

    # --- archetypes -----------------------------------------------------------
    def log_scalar(self, path: str, t: float, value: float, timeline: str = "sim_time") -> None:
        if path not in self._styled:
            self._styled.add(path)
            color = _color_for(path)
            if color is not None:  # the same colour for measured / fitted / reference in every view
                self.stream.log(path, self._rr.SeriesLines(colors=[color]), static=True)
        self._at(t, timeline)
        self.stream.log(path, self._rr.Scalars(float(value)))

    def _geometry(self, archetype: str, path, t, data, colors, radii, timeline, **extra):
        self._at(t, timeline)
        self.stream.log(path, getattr(self._rr, archetype)(data, colors=colors or _color_for(path), radii=radii,
                                                           **extra))

    def log_points3d(self, path, t, positions, colors=None, radii=None, timeline="sim_time", labels=None):
        self._geometry("Points3D", path, t, np.asarray(positions, np.float32), colors, radii, timeline, labels=labels)

    def log_points2d(self, path, t, positions, colors=None, radii=None, timeline="sim_time", labels=None):
        self._geometry("Points2D", path, t, np.asarray(positions, np.float32), colors, radii, timeline, labels=labels)

    def log_lines3d(self, path, t, strips, colors=None, radii=None, timeline="sim_time"):
        self._geometry("LineStrips3D", path, t, [np.asarray(s, np.float32) for s in strips], colors, radii, timeline)

    def log_lines2d(self, path, t, strips, colors=None, radii=None, timeline="sim_time"):
        self._geometry("LineStrips2D", path, t, [np.asarray(s, np.float32) for s in strips], colors, radii, timeline)

    def log_series(self, path: str, times: np.ndarray, values: np.ndarray, timeline: str = "sim_time") -> None:
        """A whole scalar time series in one call (columnar), for long trajectories."""
        rr = self._rr
        times = np.asarray(times, np.float64)
        if timeline == "generation":
            column = rr.TimeColumn(timeline, sequence=times.astype(np.int64))
        else:
            column = rr.TimeColumn(timeline, duration=times)
        self.stream.send_columns(path, indexes=[column],
                                 columns=rr.Scalars.columns(scalars=np.asarray(values, np.float64)))
        color = _color_for(path)
        if color is not None:
            self.stream.log(path, rr.SeriesLines(colors=[color], names=[_role(path)]), static=True)

    def log_text(self, path: str, text: str) -> None:
        self.stream.log(path, self._rr.TextDocument(text, media_type="text/markdown"), static=True)

    def close(self) -> Path:
        self._send_blueprint()
        self.stream.flush()
        self.stream.disconnect() if hasattr(self.stream, "disconnect") else None
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        try:
            self.stream.disconnect()
        finally:
            if self._tmp.exists():
                self._tmp.unlink()


class WriterFailed(RuntimeError):
    pass


class _Writer:
    """The child process that writes recordings (python -m wrenorm.viz.record_writer)."""

    def __init__(self):
        env = dict(os.environ)
        env.setdefault("RERUN_ANALYTICS", "0")
        self.proc = subprocess.Popen([sys.executable, "-m", "wrenorm.viz.record_writer"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def write(self, args: tuple, calls: list) -> None:
        data = pickle.dumps({"args": args, "calls": calls}, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            self.proc.stdin.write(len(data).to_bytes(8, "little") + data)
            self.proc.stdin.flush()
            reply = self.proc.stdout.readline().decode().strip()
        except (BrokenPipeError, OSError) as e:
            raise WriterFailed(f"the recording writer is gone ({e})") from None
        if reply != "ok":
            if not reply and self.proc.poll() is not None:
                reply = self.proc.stderr.read().decode(errors="replace").strip()[-500:]
            raise WriterFailed(reply or "the recording writer stopped")

    def stop(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=5)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()


_WRITER: _Writer | None = None


def start_writer() -> None:
    """Start the recording writer now (idempotent), if rerun-sdk is installed: it loads while the caller works."""
    global _WRITER
    if os.environ.get("WRENORM_RECORDING_WRITER", "1") == "0":  # record in this process (one core, debugging)
        return
    if (_WRITER is None or not _WRITER.alive) and rerun_available():
        import atexit

        _WRITER = _Writer()
        atexit.register(_WRITER.stop)


class Recorder:
    """The recording API (see LiveRecorder's methods): with a writer process, calls are kept and written there
    on close; otherwise they go straight to a LiveRecorder here."""

    def __init__(self, path: str | os.PathLike, application_id: str = "wrenorm", recording_id: str | None = None):
        self.path = Path(path)
        self._args = (str(path), application_id, recording_id)
        self._calls: list | None = [] if _WRITER is not None and _WRITER.alive else None
        self._live = None if self._calls is not None else LiveRecorder(path, application_id, recording_id)

    def __getattr__(self, name: str):
        if name.startswith("_") or not callable(getattr(LiveRecorder, name, None)):
            raise AttributeError(name)
        if self._live is not None:
            return getattr(self._live, name)
        return lambda *a, **k: self._calls.append((name, a, k))

    def close(self) -> Path:
        if self._live is not None:
            return self._live.close()
        try:
            _WRITER.write(self._args, self._calls)
        except WriterFailed as e:
            print(f"wrenorm: recording writer failed ({e}); writing the recording here", file=sys.stderr)
            replay(self._args, self._calls)
        return self.path

    def abort(self) -> None:
        if self._live is not None:
            self._live.abort()
        self._calls = []


def replay(args: tuple, calls: list) -> Path:
    rec = LiveRecorder(*args)
    try:
        for name, a, k in calls:
            getattr(rec, name)(*a, **k)
        return rec.close()
    except BaseException:
        rec.abort()
        raise
