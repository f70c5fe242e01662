"""Rerun recordings of a fit: reference, measured-parameter and fitted-parameter behaviour.

rerun-sdk is imported here only, so simulation and fitting run without it (the GPU machine,
minimal installs). A recording is written to a temporary file that is renamed into place on close,
so a killed run never leaves a recording that looks complete.

Importing rerun-sdk takes about half a second. Writing the recording in a second process that imports it
while the fit runs was tried and measured slower on two cores (whole `fit pd` processes, median 1.7 s against
1.1 s in-process, alternating runs): the cores are never idle enough to pay for a second interpreter.
"""
from __future__ import annotations

import os
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


class Recorder:
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
    def log_scalar(self, path: str, t: float, value: float, timeline: str = "sim_time", color=None) -> None:
        if path not in self._styled:
            self._styled.add(path)
            color = color or _color_for(path)
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
