"""Real robotic-fish marker tracks (fishsim format) -> per-rate tail kinematics and speed.

Formats (Michelis et al., srl-ethz/fishsim, MIT licence):
  markers_fX_YZ.csv         18 columns, pixel x, y of 9 markers per video frame (60 fps);
                            metres from the 0.142 m distance between the two head markers.
  rotatedMarkers_fX_YZ.csv  2 columns, metres, 9 rows per frame, rotated into the head frame
                            with the head's progress added back; used only when no pixel file
                            for that label exists (its head markers still give the forward track,
                            but the heading is constant by construction: Rate.frame "head", and
                            the head's yaw and sway cannot be measured from it).
Label X.YZ (motor rate in Hz) comes from the file name (markers_fX.YZ.csv and any case read alike; another name
that starts like a clip, markers_f1.csv, markers_f1_00_take2.csv or markers_f1_25.txt, and any other CSV whose name
holds "marker", markers_f_1_25.csv or fish_markers_f1_25.csv, is refused; other CSVs are left out with a warning,
Rate.meta "load_warnings"); the frame rate is the format's 60 fps unless given (--fps). Refused: two files of one
label and kind, an empty line between rows (a lost frame), a marker at exactly (0, 0) (a tracking dropout), rotated
files whose head markers are not ~0.142 m apart (not metres), clips in which 1 % of the frames or more repeat the
previous one exactly while the fish swims (duplicated frames; fewer are flagged) or a few in a row do (a held
tracker), frames cut out of a clip (the head's jump, in either format), a tail base not where this robot's is
(another body), tail markers that swap order along the body during the clip (a tracker swapping identities), rows
deleted from a pixel clip (every marker's step 2-4x its neighbours'), a label of 0 Hz, two clips sharing most of
their rows (one clip under two labels).
Flagged, not refused (tail_beat_check):
a tail-beat frequency far from ~0.75 x the label, which on this robot points at a wrong frame rate.

Forward speed (real and simulated alike): least-squares straight line through the head centre
(mean of markers 0 and 1) over the track, direction = principal axis of the positions, oriented
along the mean heading (marker 1 -> marker 0); speed = slope of a linear regression of the
position projected on that axis against time.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wrenorm.errors import InputError
from wrenorm.jumps import largest_jump, largest_jump_on_both_sides, repeated_runs, true_runs
from wrenorm.tasks.swimmer.options import FPS  # the fishsim format's frame rate, the --fps default

HEAD_MARKER_DISTANCE = 0.142  # m, measured on the hardware
N_MARKERS = 9
MIN_SECONDS = 2.0  # of a clip at its frame rate: less cannot hold one tail beat at the lowest rates (a count of 120
# frames had refused 5 s clips at 20 fps; stop 59)
MIN_FRAMES_PER_BEAT = 8  # frames per tail beat (at the label's expected beat), at least: fewer alias the tail's wave
# (the five clips at 60 fps: 36-160; at 20 fps the 2.25 Hz clip has 11.9)
MIN_SPEED = 0.002  # m/s; the slowest recorded rate swims 0.022 m/s
MIN_TRAVEL = 0.02  # m over the clip
HEAD_DISTANCE_RANGE = (0.5, 2.0)  # x HEAD_MARKER_DISTANCE in a rotated (metres) file; mm or cm are 10x-1000x off
TAIL_BASE_RANGE = (0.85, 1.15)  # x the robot's head-to-tail-base distance; the five clips 0.92-0.99
MAX_REPEATED_FRAMES = 0.01  # share of frames equal to the previous one while the fish swims, refused; fewer are
# flagged. Tracked video never repeats exactly while the fish moves (the five clips: none; rounded to whole pixels:
# none), and 3 % (every 33rd frame written twice, a frame-rate conversion) moved the slender drag +4 std in silence
FILLED_FRAMES = 3  # frames in a row with every marker on a straight line in time, at least: filled in (straight_runs)
REFUSED_FILL_FRAMES = 8  # ... refused from this many (shorter: said); rounded tracked clips reach 3-5 (stop 58)
CUBIC_FILL_FRAMES = 8  # frames in a row with every marker on one cubic in time (a spline's fill), said
CUBIC_GRID_STEPS = 4  # a fourth difference of numbers rounded to the grid reaches 4 grid steps (8 x half a step)
EDGE_HELD_FRAMES = 3  # whole frames repeated at a clip's start or end (a fill by bfill / ffill), said
FILLED_MARKER_FRAMES = 9  # the same for one marker, said (the fishsim clips: at most 6; at 30 fps one reaches 8)
GRID_STEPS_TO_TELL = 1.5  # straight_runs judges markers moving at least this many grid steps a frame (median)
GLITCH_GRID_STEPS = 4  # a tail marker's jump must pass this many steps of the file's number grid to be a glitch
LIKELY_RUN = 1e-3  # ... and longer than a run with this chance in the clip at the rate its frames come elsewhere
MAX_HELD_FRAMES = 3  # frames in a row equal to the one before: a tracker holding its last position (11 held frames of
# one clip moved the slender drag 4x and the viscosity 2.3x, with the head's jump under its limit)
TAIL_MARKER_MIN_GAP = 0.005  # m along the body: tail markers closer than this track one point
MAX_SWAPPED_FRAMES = 3  # frames in a row with a tail marker that far ahead of the one before it (the five clips: none)
MAX_HEAD_JUMP = 10.0  # x the head's median step around it (wrenorm.jumps): built-in clips 1.4-3.3, a second cut out 47
# What a clip's own motion says about how it was filmed and swum (clip_flags; flagged, not refused). Each limit is
# about twice the largest the five fishsim clips show, and each case past it moved coefficients by several of their
# stds in silence (a probe of stop 46):
MAX_BEAT_SPEED_CHANGE = 0.2  # a complete beat's speed off the clip's median beat by this share: not cruising (the five
# clips: 0.05; a start from rest over 2 s: 0.37-0.86, slender and angular drag 3.5x)
MAX_TURN_DEG = 25.0  # the beat-averaged heading's range over the clip (the five: 1-16; a 1 m circle: 55, viscosity 0)
MAX_HEAD_SCATTER = 0.028  # std of the second difference of the head markers' distance / that distance: tracking noise
# (the five: 0.011-0.014; 2 px of noise 0.050-0.056, slender drag 3x)
MAX_HEAD_DRIFT = 0.10  # the head markers' pixel distance, last third of the clip against the first: the pixel scale
# changes along the path, as under a tilted camera (the five: -0.016 to -0.051; tilted 20-30 deg: up to 0.16)
MAX_TAIL_JUMP = 10.0  # x the larger median step of a tail marker before and after it, in the head frame, for two or
# more tail markers at one frame: two takes joined (the five clips: at most 4.6-6.3; seams: 10-24 on 2-3 markers)
MAX_STEP_RATIO = 1.8  # a frame step along the mean of the steps either side of it, all markers but the one that
# deviates most (_check_dropped_rows): a row deleted makes it ~2, two ~3, three ~4. The five clips at 60 fps: at most
# 1.29; resampled to 25/30/50/120 fps: 1.35, but 1.64 for the 0.50 Hz clip at 120 fps (sub-pixel steps). Rows deleted
# in runs of 1-3 (4 % of the rows): 2.5-4.1, speeds 5 % fast. A single deleted row (ratio 1.6-1.9 under the pixel
# noise) goes unseen alone; so do deletions in the 0.50 Hz clip, whose markers move ~1 px a frame
CLEAR_STEP_RATIO = 2.5  # .. one such step alone must reach this (two rows or more), else two steps must pass 1.8:
# a foreign clip slower or finer than these (the 0.50 Hz clip at 120 fps: 1.64) may reach 1.8 once by noise
UNEVEN_STEP_SPREAD = 1.2  # 95th percentile of those ratios above this: frames at uneven times, said beside deleted
# rows when refusing (the five clips: 0.67-1.07; 4 ms of jitter at 60 fps: 1.3-1.6)
HEAD_FLEX = 0.05  # relative std of the head markers' distance above this, with the last two markers' below half of
# it, is a clip written tail first (the head: 0.4-2.9 % in the five clips, with 1 px of noise, rounded or resampled;
# the last two markers 2.6-13 %)
MAX_SHARED_ROWS = 0.5  # share of the shorter clip's rows found exactly in another clip: one track under two labels
TAIL_BEAT_PER_LABEL = 0.75  # this robot's tail-beat frequency / motor-rate label (fishsim README)
TAIL_BEAT_PER_LABEL_RANGE = (0.70, 0.80)  # about +-7 %, outside: flagged. The five clips lie at 0.738-0.756, and the
# three more of fishsim's repository (0.75, 1.50, 2.00 Hz), not seen when this was set, at 0.746-0.752; a frame rate off
# by 2x lands at 0.375 or 1.5, clips at 50 or 72 fps read at 60 at 0.90 or 0.62 (0.5-1.0 until stop 44 let those by),
# and at 55 or 66 fps at 0.81-0.82 or 0.67-0.69, which +-15 % (until stop 54) let by with every speed 9 % off
# fishsim's names, markers_f1_00.csv; a decimal point (markers_f1.00.csv) and any case of the letters read alike
_NAME = re.compile(r"^(markers|rotatedMarkers)_f(\d+)[_.](\d+)\.csv$", re.IGNORECASE)
_CLIP_LIKE = re.compile(r"^(markers|rotatedmarkers)_f\d", re.IGNORECASE)
# a text table under another extension is meant as a clip too (markers_f1_25.txt was left out in silence, the fit
# running on one rate fewer); a plot, an editor's backup or a folder beside the clips is not
CLIP_LIKE_SUFFIXES = (".csv", ".txt", ".tsv", ".dat", "")
_MARKER_LIKE = re.compile(r"marker.*\.csv$", re.IGNORECASE)  # any CSV naming markers is meant as a clip
BUILTIN = "fishsim_kinematics.npz"
# A rotatedMarkers file's forward track is the head's frame-to-frame steps measured along the head's own axis, which
# yaws with every beat, and summed (its marker-0 x follows that sum within 3-5 mm over the clip), with a sideways drift
# summed alike: a path along the wobble, longer than the straight line, so its speed comes out high. The five fishsim
# clips, rotated file against pixel file, same rule (measured_speed): +7.5 % (0.50 Hz), +6.7 (1.00), +4.8 (1.25),
# +2.7 (1.75), +0.8 (2.25), most where the head wobbles much for little progress
ROTATED_SPEED_NOTE = ("the forward speed of a rotatedMarkers clip is read from a track that sums the head's "
                      "frame-to-frame steps along its yawing axis: 0.8-7.5 % above the same clip's markers_*.csv "
                      "(straight-line) speed on the five fishsim clips, most at the lowest rates (0.50 Hz +7.5 %, "
                      "2.25 Hz +0.8 %); give the markers_*.csv where there is one")


@dataclass
class Rate:
    """One recorded motor rate: marker tracks in metres and what we derive from them."""
    label: float
    markers: np.ndarray          # (frames, 9, 2) metres
    source: str = ""
    fps: float = FPS
    frame: str = "world"         # "world" (markers_*.csv, built-in); "head" (rotatedMarkers: heading constant)
    tail_freq: float = 0.0       # Hz, tail-beat frequency
    speed: float = 0.0           # m/s, measured forward speed
    yaw_amp: float = 0.0         # rad, amplitude of the head's yaw oscillation at tail_freq
    meta: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"f{self.label:.2f}"


# --- loading ---------------------------------------------------------------------------------

def _label_of(path: Path) -> tuple[str, float] | None:
    m = _NAME.match(path.name)
    if not m:
        return None
    return ("markers" if m.group(1).lower() == "markers" else "rotatedMarkers"), float(f"{m.group(2)}.{m.group(3)}")


def _read_csv(path: Path, columns: int) -> np.ndarray:
    """The file's rows of numbers; a refusal's row is the file's own line. Read line by line rather than by np.loadtxt,
    which skips empty lines: in a clip whose rows are its frames, an empty line is a lost frame, and skipped it made
    the clip swim fast (an empty line for every 25th row of the 0.50 Hz clip: speed and tail beat +4 %, in silence)."""
    try:
        # utf-8-sig: spreadsheet exports start with a byte-order mark, which is no part of the first number
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(str(path), "contents", f"not a numeric CSV (not UTF-8 text: {exc.reason} at byte "
                         f"{exc.start})") from None
    except OSError as exc:  # a dangling link (git-annex data not fetched), no permission
        raise InputError(str(path), "file", f"cannot be read: {exc.strerror or exc}") from None
    raw = text.splitlines()
    comment = [line.lstrip().startswith("#") for line in raw]  # a comment line is no frame, lost or not
    lines = [line.split("#", 1)[0] for line in raw]  # comments, whole-line or after a row, as loadtxt read them
    numbered = [(i + 1, line) for i, line in enumerate(lines) if line.strip()]
    if not numbered:
        raise InputError(str(path), "contents", "empty file: no rows of numbers")
    first, last = numbered[0][0], numbered[-1][0]
    empty = next((n for n in range(first, last) if not lines[n - 1].strip() and not comment[n - 1]), None)
    if empty is not None:
        raise InputError(str(path), f"row {empty}", "empty line between rows: each row is one frame, so an empty "
                         "line is a frame lost (skipped, the clip would swim too fast); give the frame, or remove the "
                         "line if it is not one")
    data = np.empty((len(numbered), columns))
    for row, (n, line) in enumerate(numbered):
        cells = line.split(",")
        for col, cell in enumerate(cells):
            try:
                value = float(cell)
            except ValueError:
                shown = cell.strip() if len(cell.strip()) <= 40 else cell.strip()[:40] + "..."
                what = f"{shown!r} is not a number" if cell.strip() else "empty cell"
                raise InputError(str(path), f"row {n} column {col + 1}", f"not a numeric CSV: {what}") from None
            if col < columns:
                data[row, col] = value
        if len(cells) != columns:
            raise InputError(str(path), "columns", f"expected {columns} comma-separated columns, found {len(cells)} "
                             f"in row {n}")
    bad = ~np.isfinite(data)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise InputError(str(path), f"row {numbered[row][0]} column {col + 1}", "value is NaN or infinite")
    return data


def read_pixel_markers(path: Path, fps: float = FPS) -> np.ndarray:
    """markers_*.csv -> (frames, 9, 2) metres (scale from the head-marker distance)."""
    return _read_pixel(path, fps)[1]


def _check_duration(path: Path, frames: int, fps: float) -> None:
    least = int(np.ceil(MIN_SECONDS * fps - 1e-9))
    if frames < least:
        raise InputError(str(path), "rows", f"{frames} frames, {frames / fps:.3g} s at {fps:g} fps: need at least "
                         f"{MIN_SECONDS:g} s ({least} frames; give --fps if the clip was filmed at another rate)")


def _read_pixel(path: Path, fps: float = FPS) -> tuple[np.ndarray, np.ndarray]:
    """markers_*.csv -> its rows as read (frames, 18) and the markers (frames, 9, 2) in metres."""
    data = _read_csv(path, 2 * N_MARKERS)
    _check_duration(path, len(data), fps)
    markers = data.reshape(-1, N_MARKERS, 2)
    _check_dropouts(path, markers, range(N_MARKERS), rows_per_frame=1)
    _check_repeated_frames(path, markers)
    _check_filled(path, markers, range(N_MARKERS), rows_per_frame=1)
    _check_head(path, markers, rows_per_frame=1)
    _check_jumps(path, markers, rows_per_frame=1)
    head_px = np.linalg.norm(markers[:, 1] - markers[:, 0], axis=1).mean()
    return data, markers * (HEAD_MARKER_DISTANCE / head_px)


def _check_dropouts(path: Path, markers: np.ndarray, which, rows_per_frame: int) -> None:
    """A marker at exactly (0, 0) is a tracker that lost it and wrote zeros: used, it drags the scale, the head
    track or the tail wave to the image corner for those frames."""
    which = list(which)
    zero = np.all(markers[:, which] == 0.0, axis=-1)
    if zero.any():
        frame, k = np.argwhere(zero)[0]
        marker = which[k]
        row = frame * rows_per_frame + (marker + 1 if rows_per_frame > 1 else 1)
        raise InputError(str(path), f"row {row} marker {marker}", f"at exactly (0, 0) in frame {frame + 1} "
                         f"({int(zero.sum())} such markers in the clip): a tracking dropout? interpolate those markers "
                         "from the frames either side (rows removed would be read as frames cut out of the clip; "
                         f"{REFUSED_FILL_FRAMES} frames or more of the whole fish on a straight line in a row, or "
                         f"{2 * REFUSED_FILL_FRAMES} over the clip, are refused ({FILLED_FRAMES} or more said), and "
                         f"{FILLED_MARKER_FRAMES} or more of one marker said, since they erase the motion within the "
                         "beat: cut the clip at a longer gap)")


def moving_repeats(markers: np.ndarray) -> list[tuple[int, int]]:
    """Runs of frames equal to the one before while the fish swims: (first copy, copies). A fish at rest may repeat
    (half-pixel steps), so only repeats inside motion count: the head goes at least half its usual pace across them."""
    head = 0.5 * (markers[:, 0] + markers[:, 1])
    step = np.linalg.norm(np.diff(head, axis=0), axis=1)
    usual = float(np.median(step[step > 0])) if np.any(step > 0) else 0.0
    return [(first, n) for first, n, moved, span in repeated_runs(markers, head) if moved > 0.5 * usual * span]


def _resolution(markers: np.ndarray) -> float:
    """The file's number grid: the least nonzero change of any coordinate between frames that recurs (half a pixel in
    the fishsim clips; a millimetre in metres written to 3 decimals); a few off-grid values (a dropout mended by
    unrounded interpolation) do not make it finer. Where no change recurs (unrounded numbers), the least one."""
    steps = np.abs(np.diff(markers.reshape(len(markers), -1), axis=0)).ravel()
    steps = steps[steps > 0]
    if not steps.size:
        return 0.0
    values, counts = np.unique(steps, return_counts=True)
    recurring = values[counts >= max(3, int(0.001 * steps.size))]
    return float(recurring.min()) if recurring.size else float(values[0])


def _too_slow_to_tell(markers: np.ndarray, group: list[int], grid: float) -> bool:
    """Whether the markers `group` move under GRID_STEPS_TO_TELL steps of the file's grid a frame (median): a tracked
    marker that slow steps evenly, on a line or a cubic, as often as a filled one."""
    return float(np.median(np.linalg.norm(np.diff(markers[:, group], axis=0), axis=2))) < GRID_STEPS_TO_TELL * grid


def _swimming(markers: np.ndarray, reference: list[int], pace: float):
    """Whether the fish swims across a run of frames: (first, last) -> bool, the mean of the markers `reference` (the
    others beside one marker; for a whole fish, all) going at least `pace` of its median pace a frame."""
    ref = markers[:, reference].mean(axis=1)
    usual = float(np.median(np.linalg.norm(np.diff(ref, axis=0), axis=1)))
    return lambda first, last: bool(np.linalg.norm(ref[last] - ref[first]) > pace * usual * (last - first))


def straight_runs(markers: np.ndarray, which) -> list[tuple[int, int, tuple]]:
    """Runs of frames in which the markers `which` (all together, or one alone) move on a straight line at constant
    speed or stand still while the other markers swim on (at least half their usual pace across the run): (first
    frame, frames, markers), at least FILLED_FRAMES long (one marker: FILLED_MARKER_FRAMES) and longer than a run with
    LIKELY_RUN of a chance at the rate such frames come in the clip's short runs. On a line means every coordinate's
    second difference within the file's number grid, and the whole run (or it less a frame at either end) within a
    grid step of the line fitted through it: a slow marker on a coarse grid (integer pixels, millimetres) steps evenly
    for a dozen frames and more, but its beat curves it away from any line over them; markers slower than
    GRID_STEPS_TO_TELL grid steps a frame are not judged. The fishsim clips have no such run (one marker at most 6
    frames, all nine at once none). A tracker's gap filling and pandas' interpolate or ffill write them, and they erase
    the head's sway and surge within the beat: 15 frames of the whole fish filled twice had moved blunt drag -3.7 stds
    and viscosity +4 stds, and one head marker held for 10 frames the same, in silence (a probe of stop 58)."""
    which = list(which)
    grid = _resolution(markers) * (1 + 1e-9) + 1e-12 * np.abs(markers).max()
    d2 = np.abs(np.diff(markers[:, which], 2, axis=0))  # (T-2, len(which), 2): d2[k] centred on frame k + 1
    line = np.all(d2 <= grid, axis=2)
    out = []
    for group in [which] + [[m] for m in which]:
        least = FILLED_FRAMES if len(group) > 1 else FILLED_MARKER_FRAMES
        on = np.all(line[:, [which.index(m) for m in group]], axis=1)
        runs = true_runs(on)
        # how often such frames come in the clip's own short runs (long runs, the candidates, left out: several
        # fills must not make each other likely)
        short = sum(n for _, n in runs if n < least)
        share = short / max(len(on) - (on.sum() - short), 1)
        if share >= 1.0:
            continue  # every frame on a line: this marker's motion is below the file's grid
        if share > 0.0:  # a run this long has less than LIKELY_RUN of a chance in the clip at that rate
            least = max(least, int(np.ceil(np.log(LIKELY_RUN / len(on)) / np.log(share))))
        if _too_slow_to_tell(markers, group, grid):
            continue
        # swimming across the run: the other markers at half their usual pace; a whole fish filled moves at its two
        # ends' mean pace, which a slow beat's stretch can bring under half the median: a quarter, still not at rest
        whole = len(group) > 1
        others = list(range(markers.shape[1])) if whole else [m for m in range(markers.shape[1]) if m not in group]
        swims = _swimming(markers, others, 0.25 if whole else 0.5)
        for a, n in runs:  # frames a + 1 .. a + n lie on the line through frames a and a + n + 1
            if n < least or not swims(a, a + n + 1):
                continue
            # the whole run within a grid step of one line; a real frame beside a fill may extend the run by one
            # on either side without lying on the fill's line
            for lo, hi in ((a, a + n + 1), (a + 1, a + n + 1), (a, a + n), (a + 1, a + n)):
                if hi - lo - 1 < least:
                    continue
                pts = markers[lo:hi + 1, group].reshape(hi - lo + 1, -1)
                t = np.arange(hi - lo + 1, dtype=np.float64)
                fit = np.polynomial.polynomial.polyfit(t, pts, 1)
                if np.abs(pts - np.polynomial.polynomial.polyval(t, fit).T).max() <= grid:
                    out.append((lo + 1, hi - lo - 1, tuple(group)))
                    break
    return out


def _check_filled(path: Path, markers: np.ndarray, which, rows_per_frame: int) -> None:
    """Every marker on a straight line at once for REFUSED_FILL_FRAMES or more, or for twice that over the clip's runs,
    is refused (straight_runs; fewer are said by feature_flags, as one marker alone is: a clip rounded to whole pixels
    at half resolution had shown runs of 3-5 frames in about 1 of 50 rotations; many short fills add up, 15 of 4
    frames filling one frame in five)."""
    whole = [(f, n) for f, n, m in straight_runs(markers, which) if len(m) > 1]
    lengths = [n for _, n in whole]
    if whole and (max(lengths) >= REFUSED_FILL_FRAMES or sum(lengths) >= 2 * REFUSED_FILL_FRAMES):
        first, n = max(whole, key=lambda r: r[1])
        rows = f"{first * rows_per_frame + 1}-{(first + n) * rows_per_frame}"
        more = f" ({len(whole)} such runs, {sum(lengths)} frames in all)" if len(whole) > 1 else ""
        raise InputError(str(path), f"rows {rows}", f"every marker moves on a straight line at constant speed for {n} "
                         f"frames (frames {first + 1}-{first + n}){more} while the fish swims: filled in by "
                         "interpolation? that erases the head's sway and surge within the beat, which the fit "
                         "reads (15 frames so filled twice moved blunt drag by 3.7 stds); give the tracked frames, or "
                         "cut the clip there")


def cubic_runs(markers: np.ndarray, which) -> list[tuple[int, int]]:
    """Runs of frames in which every marker of `which` lies on one cubic in time while the fish swims: (first frame,
    frames), CUBIC_FILL_FRAMES or more. A spline, PCHIP or Akima fill of a gap is one cubic piece between the tracked
    frames either side, so its frames' fourth differences vanish (within CUBIC_GRID_STEPS of the file's grid when
    written rounded); the fishsim clips have no frame where all nine markers' do, nor their copies rounded to whole
    pixels more than one. 20 frames so filled twice had moved blunt drag -3.4 stds and viscosity +5 and loaded as a
    straight fill would not (review of stop 58)."""
    which = list(which)
    if len(markers) < 5:
        return []
    resolution = _resolution(markers)
    grid = resolution * CUBIC_GRID_STEPS * (1 + 1e-9) + 1e-12 * np.abs(markers).max()
    d4 = np.abs(np.diff(markers[:, which], 4, axis=0))  # d4[k] spans frames k .. k + 4
    if np.median(d4.max(axis=(1, 2))) < 2.0 * grid:
        return []  # a clip this smooth on its grid (fast frames, noise under a grid step) is a cubic everywhere
    on = np.all(d4 <= grid, axis=(1, 2))
    if _too_slow_to_tell(markers, which, resolution):
        return []
    swims = _swimming(markers, which, 0.25)
    out = []
    for a, n in true_runs(on):  # frames a + 2 .. a + n + 1 lie inside the cubic through frames a .. a + n + 3
        frames = n + 2  # the frames between the two tracked ones either side that the cubic needs
        if frames >= CUBIC_FILL_FRAMES and swims(a, a + n + 3):
            out.append((a + 1, frames))
    return out


def held_edges(markers: np.ndarray) -> list[tuple[int, int]]:
    """Whole frames repeated exactly at the clip's start or end, EDGE_HELD_FRAMES or more: (first frame, frames). A
    tracker's first or last position copied over frames it lost (pandas' bfill / ffill, interpolate with
    limit_direction="both"); repeats inside the clip are moving_repeats', which at the edges cannot see motion across
    them. 12 such frames at both ends of the 1.00 Hz clip had moved blunt drag -1.65 stds in silence (review of stop
    58). A fish filmed at rest before it swims holds too, at a pixel's rounding; the clip must cruise anyway."""
    return [(first - 1, n + 1) for first, n, _, _ in repeated_runs(markers, markers[:, 0])  # copies of frame first - 1
            if (first == 1 or first + n == len(markers)) and n + 1 >= EDGE_HELD_FRAMES]


def _check_repeated_frames(path: Path, markers: np.ndarray) -> None:
    """Tracked video jitters by at least a pixel's rounding from frame to frame while the fish swims: frames equal to
    the one before are a lower frame rate written out at a higher one (each copy slows the speed and the tail beat
    by its share), and a few in a row a tracker holding its last position."""
    runs = moving_repeats(markers)
    if runs and max(n for _, n in runs) >= MAX_HELD_FRAMES:
        first, n = max(runs, key=lambda r: r[1])
        raise InputError(str(path), f"frames {first + 1}-{first + n}", f"{n} frames in a row repeat the one before "
                         "exactly while the fish swims: a tracker holding its last position? give the clip with those "
                         "frames tracked, or cut before them")
    copies = sum(n for _, n in runs)
    share = copies / (len(markers) - 1)
    if share >= MAX_REPEATED_FRAMES:
        raise InputError(str(path), "rows", f"{copies} of {len(markers)} frames ({100 * share:.1f} %) "
                         "repeat the previous frame exactly while the fish swims: duplicated frames; remove the copies "
                         "and give the clip's true frame rate with --fps")


def _check_jumps(path: Path, markers: np.ndarray, rows_per_frame: int) -> None:
    """Rows are frames at one rate with no time column, so frames cut out of a clip leave only a jump of the head:
    read through, the clip swims that far in one frame and its speed comes out too high (a second cut from the
    1.00 Hz clip: +36 %). A rotated file's head markers keep the head's progress, so the jump shows there too."""
    head = 0.5 * (markers[:, 0] + markers[:, 1])
    frame, ratio = largest_jump(np.linalg.norm(np.diff(head, axis=0), axis=1))
    if ratio > MAX_HEAD_JUMP:
        first, last = frame * rows_per_frame + 1, (frame + 2) * rows_per_frame
        raise InputError(str(path), f"rows {first}-{last}", f"the head jumps {ratio:.0f} x its frame-to-frame "
                         f"step around there between frames {frame + 1} and {frame + 2}: frames missing or a tracking "
                         "jump; give the clip without gaps")


def _check_dropped_rows(path: Path, markers: np.ndarray, rows_per_frame: int) -> None:
    """Rows are frames at one rate with no time column, so rows deleted where the tracker lost the fish for a frame or
    three leave a step of every marker 2-4x the steps either side of it, under the head's jump limit: read through, the
    clip swims too fast (rows deleted in runs of 1-3, 4 % of them: speeds +5 %, coefficients several stds off). With
    d_k all markers' step from frame k to k+1 and p_k = (d_{k-1} + d_{k+1}) / 2, the step's ratio (d_k . p_k) /
    (p_k . p_k) is ~1 in a clip and ~n + 1 where n rows are missing; the marker that raises it most is left out of
    the sums, so one marker's tracking glitch is no deleted row (the 0.50 Hz clip's marker 5 jumps 13 px once)."""
    d = np.diff(markers, axis=0)
    if len(d) < 3:
        return
    p, c = 0.5 * (d[:-2] + d[2:]), d[1:-1]
    num, den = np.einsum("kij,kij->ki", c, p), np.einsum("kij,kij->ki", p, p)
    k, worst = np.arange(len(num)), np.argmax(num - den, axis=1)
    num_rest, den_rest = num.sum(axis=1) - num[k, worst], den.sum(axis=1) - den[k, worst]
    ratio = np.where(den_rest > 0, num_rest / np.where(den_rest > 0, den_rest, 1.0), 0.0)
    held = ~np.any(d != 0, axis=(1, 2))  # a frame that repeats the one before is _check_repeated_frames' (one or two
    ratio[held[:-2] | held[2:]] = 0.0  # in a row pass it: a pixel's rounding), and the step after it makes up for it
    big = np.nonzero(ratio >= MAX_STEP_RATIO)[0]
    if not big.size or (big.size < 2 and ratio.max() < CLEAR_STEP_RATIO):  # one step near the noise is no evidence
        return
    j = int(big[np.argmax(ratio[big])])  # the step from frame j + 1 to j + 2 (0-based)
    first, last = (j + 1) * rows_per_frame + 1, (j + 3) * rows_per_frame
    frames = ", ".join(f"{b + 2}-{b + 3}" for b in big[:6]) + (", ..." if len(big) > 6 else "")
    steps = f"{len(big)} such step{'s' if len(big) > 1 else ''} in the clip, between frames {frames}"
    # frames at uneven times (a webcam's clock) raise every step's ratio a little, deleted rows a few steps much:
    # 4 ms of jitter at 60 fps had been refused as rows deleted alone (stop 58's probe; the five clips' 95th
    # percentile 0.67-1.07, that jitter's 1.3-1.6)
    steady = ratio[(ratio != 0.0) & (ratio < MAX_STEP_RATIO)]  # the steps that are no deleted rows themselves (5 %
    # of single rows deleted had put them in the percentile and the note on a steady clock; review of stop 59)
    spread = float(np.quantile(steady, 0.95)) if steady.size else 0.0
    jitter = (f" (the steps vary throughout the clip: 95 % of them within {spread:.2f} x their neighbours', a steady "
              "camera's clip with no rows deleted within 1.1 x: frames at uneven times, or rows deleted throughout? "
              "rows are read at one rate, so resample a clip with uneven times to its frame rate)"
              if spread > UNEVEN_STEP_SPREAD else "")
    raise InputError(str(path), f"rows {first}-{last}", f"every marker steps {ratio[j]:.1f} x the mean of its steps "
                     f"either side between frames {j + 2} and {j + 3} ({steps}){jitter}: rows deleted where the "
                     "tracker lost the fish? rows are read as consecutive frames, so the clip would swim too fast; put "
                     "the lost frames back, interpolated from the frames either side (no NaN or empty rows are read; "
                     f"{REFUSED_FILL_FRAMES} or more frames so filled in a row, or {2 * REFUSED_FILL_FRAMES} over the "
                     f"clip, are refused, {FILLED_FRAMES} or more said: cut the clip there instead)")


def _check_head(path: Path, markers: np.ndarray, rows_per_frame: int) -> None:
    """The head frame (heading, pixel scale) needs head markers 0 and 1 apart in every frame."""
    apart = np.linalg.norm(markers[:, 1] - markers[:, 0], axis=1) > 0
    if not apart.all():
        frame = int(np.argmin(apart))
        raise InputError(str(path), f"row {frame * rows_per_frame + 1} markers 0 and 1",
                         f"head markers coincide in frame {frame + 1}: no heading")


def read_rotated_markers(path: Path, fps: float = FPS) -> np.ndarray:
    """rotatedMarkers_*.csv -> (frames, 9, 2) metres."""
    data = _read_csv(path, 2)
    if len(data) % N_MARKERS:
        raise InputError(str(path), "rows", f"{len(data)} rows is not a multiple of {N_MARKERS} markers")
    markers = data.reshape(-1, N_MARKERS, 2)
    _check_duration(path, len(markers), fps)
    # marker 0 is the head frame's origin, at (0, 0) in the first frame by construction
    _check_dropouts(path, markers, range(1, N_MARKERS), rows_per_frame=N_MARKERS)
    _check_repeated_frames(path, markers)
    _check_filled(path, markers, range(1, N_MARKERS), rows_per_frame=N_MARKERS)
    _check_head(path, markers, rows_per_frame=N_MARKERS)
    _check_jumps(path, markers, rows_per_frame=N_MARKERS)
    # no _check_dropped_rows: in the head frame the steps of the tail markers are the tail's own wave and the head's
    # track a sum of steps along its yawing axis; the five rotated files reach 2.1-2.9 in full, as if rows were missing
    # no pixel scale here: the file must already be in metres (a mm or cm export would swim at km/h)
    apart = float(np.linalg.norm(markers[:, 1] - markers[:, 0], axis=1).mean())
    lo, hi = (HEAD_MARKER_DISTANCE * f for f in HEAD_DISTANCE_RANGE)
    if not lo <= apart <= hi:
        raise InputError(str(path), "units", f"head markers 0 and 1 are {apart:.4g} (file units) apart on average, "
                         f"{HEAD_MARKER_DISTANCE} m on the robot: metres expected (millimetres or centimetres?)")
    return markers


def _check_body(path, markers: np.ndarray) -> None:
    """The tail-base marker is rigid with the head: its distance from the head's midpoint is this robot's
    (body.TAIL_BASE_X - HEAD_REF_X, 0.286 m; the five clips 0.263-0.282 in median). Far from it the clip is of
    another body, whose tail the model's fixed geometry cannot be: a tail 1.4x as long was fitted, every coefficient
    "determined", angular drag 8x."""
    from wrenorm.tasks.swimmer.body import HEAD_REF_X, TAIL_BASE_X

    nominal = TAIL_BASE_X - HEAD_REF_X
    d = float(np.median(np.linalg.norm(markers[:, 2] - 0.5 * (markers[:, 0] + markers[:, 1]), axis=1)))
    lo, hi = (nominal * f for f in TAIL_BASE_RANGE)
    if not lo <= d <= hi:
        raise InputError(str(path), "marker 2", f"the tail base lies {d:.3f} m from the head's midpoint (median), "
                         f"{nominal:.3f} m on this robot (accepted {lo:.3f}-{hi:.3f}): another fish, or markers in "
                         "another order? the model's body is this robot's")


def check_fps(fps, source: str = "--fps") -> float:
    fps = float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(source, "fps", f"frame rate must be a positive number of frames per second, got {fps:g}")
    return fps


def load_dir(path, fps: float = FPS) -> list[Rate]:
    """Every markers_f*.csv (else rotatedMarkers_f*.csv) in `path`, sorted by label; `fps` frames per second."""
    path = Path(path)
    fps = check_fps(fps)
    if not path.is_dir():
        raise InputError(str(path), "--data", "is a file: name the folder that holds the markers_f*.csv clips"
                         if path.exists() else "directory not found")
    by_kind: dict[tuple[str, float], Path] = {}
    notes = []  # CSVs left out, said with the clips' flags (Rate.meta "load_warnings")
    for f in sorted(path.iterdir()):
        if f.name.startswith("."):  # hidden: a Mac's ._markers_f1_00.csv beside each clip copied off it
            continue
        got = _label_of(f)
        if got is None:
            clip_like = f.is_file() and _CLIP_LIKE.match(f.name) and f.suffix.lower() in CLIP_LIKE_SUFFIXES
            if clip_like or (f.is_file() and _MARKER_LIKE.search(f.name)):
                # meant as a clip (markers_f_1_25.csv, fish_markers_f1_25.csv): left out, the fit would run on
                # fewer rates in silence
                raise InputError(str(f), "file name", "looks like a clip but is not named markers_fX_YZ.csv or "
                                 "rotatedMarkers_fX_YZ.csv (label X.YZ Hz, e.g. markers_f2_25.csv or "
                                 "markers_f2.25.csv): rename it, or move it out of the folder")
            if f.is_file() and f.suffix.lower() == ".csv":
                notes.append(f"{f}: not read: only markers_fX_YZ.csv and rotatedMarkers_fX_YZ.csv files are clips")
            continue
        if got[1] <= 0:  # the label is the motor rate, and the tail-beat check divides by it
            raise InputError(str(f), "label", f"{got[1]:.2f} Hz: the motor rate in the name must be positive "
                             "(markers_fX_YZ.csv, X.YZ Hz)")
        if got in by_kind:  # markers_f1_0.csv and markers_f1_00.csv: keeping either would hide the other
            raise InputError(str(path), "file names", f"{by_kind[got].name} and {f.name} both hold label "
                             f"{got[1]:.2f} Hz: keep one")
        by_kind[got] = f
    found: dict[float, tuple[str, Path]] = {}
    for (kind, label), f in by_kind.items():
        if label not in found or kind == "markers":
            found[label] = (kind, f)
    if not found:
        raise InputError(str(path), "--data", "no markers_f*.csv or rotatedMarkers_f*.csv files")
    rates, rows = [], []
    for label in sorted(found):
        kind, f = found[label]
        if kind == "markers":
            raw, markers = _read_pixel(f, fps)
        else:
            markers = read_rotated_markers(f, fps)
            raw = markers.reshape(len(markers), -1)
        rows.append((f, kind, raw))
        rates.append(analyse(Rate(label=label, markers=markers, source=f.name, fps=fps,
                                  frame="world" if kind == "markers" else "head")))
        if kind == "markers":  # after the clip's own checks: a more telling refusal (a tail with no beat) comes first
            _check_dropped_rows(f, raw.reshape(len(raw), N_MARKERS, 2), rows_per_frame=1)
    _check_copies(rows)
    for r in rates:
        r.meta["load_warnings"] = list(notes)
    return rates


def _check_copies(rows: list[tuple[Path, str, np.ndarray]]) -> None:
    """Tracked video never gives two clips the same rows: most rows of one clip found exactly in another is one track
    delivered under two labels (a held-out clip that copies a training clip validates the fit on its own data), also
    when one is a trimmed copy of the other."""
    seen = [(f, kind, len(raw), {r.tobytes() for r in np.ascontiguousarray(raw)}) for f, kind, raw in rows]
    for i, (f, kind, raw) in enumerate(rows):
        for g, kind_g, n_g, other in seen[:i]:
            if kind_g != kind:  # pixels against metres: no row can match
                continue
            shared = sum(r.tobytes() in other for r in np.ascontiguousarray(raw))
            if shared > MAX_SHARED_ROWS * min(len(raw), n_g):
                raise InputError(str(f), "rows", f"{shared} of its {len(raw)} rows are rows of {g} ({n_g} rows), "
                                 "exactly: one clip under two labels (a copy, or a trimmed copy)? each label needs "
                                 "its own recording")


def tail_beat_check(rates: list[Rate]) -> dict:
    """Tail-beat frequency / label of each clip against this robot's ~0.75: far off, the frame rate is the usual
    culprit (a 120 fps clip read at 60 fps halves it). Flagged, not refused: another robot may beat otherwise."""
    lo, hi = TAIL_BEAT_PER_LABEL_RANGE
    ratios = {f"{r.label:.2f}": r.tail_freq / r.label if r.label > 0 else None for r in rates}
    flagged = [f"{r.source or r.name}: tail-beat frequency {r.tail_freq:.3f} Hz is {ratio:.2f} x the label "
               f"{r.label:.2f} Hz, this robot beats at ~{TAIL_BEAT_PER_LABEL} x: is the frame rate ({r.fps:g} fps) "
               f"right? (--fps)" for r, ratio in zip(rates, ratios.values())
               if ratio is not None and not lo <= ratio <= hi]
    return {"tail_beat_per_label": ratios, "expected": TAIL_BEAT_PER_LABEL, "accepted_range": [lo, hi],
            "fps": sorted({r.fps for r in rates}), "flagged": flagged}


def parse_labels(text, rates: list[Rate], source: str = "--train") -> list[float]:
    """Training labels, given as a list of numbers or as comma-separated text, matched to the loaded rates."""
    labels = []
    items = str(text).split(",") if isinstance(text, str) else list(text)
    for item in items:
        item = str(item).strip()
        try:
            value = float(item)
        except ValueError:
            raise InputError(source, item or "(empty)", "not a number") from None
        match = [r.label for r in rates if abs(r.label - value) < 1e-6]
        if not match:
            raise InputError(source, item, f"no data for this rate; available: {[f'{r.label:.2f}' for r in rates]}")
        labels.append(match[0])
    if len(set(labels)) != len(labels):
        raise InputError(source, text, "repeated rate")
    if len(labels) == len(rates):
        raise InputError(source, text, "every rate is a training rate; leave at least one for validation")
    return labels


# --- analysis --------------------------------------------------------------------------------

def head_frame(markers: np.ndarray) -> np.ndarray:
    """World markers -> head frame: origin marker 0, x along marker 0 -> marker 1 (towards the tail)."""
    e = markers[:, 1] - markers[:, 0]
    e = e / np.linalg.norm(e, axis=1, keepdims=True)
    rel = markers - markers[:, :1]
    x = rel[..., 0] * e[:, None, 0] + rel[..., 1] * e[:, None, 1]
    y = -rel[..., 0] * e[:, None, 1] + rel[..., 1] * e[:, None, 0]
    return np.stack([x, y], axis=-1)


def line_speed(t: np.ndarray, pos: np.ndarray, heading: np.ndarray) -> float:
    """Slope of the straight-line fit of pos (N,2) along its principal axis, oriented by heading."""
    p = pos - pos.mean(axis=0)
    cov = p.T @ p / len(p)
    ang = 0.5 * np.arctan2(2 * cov[0, 1], cov[0, 0] - cov[1, 1])
    d = np.array([np.cos(ang), np.sin(ang)])
    if d @ heading.sum(axis=0) < 0:
        d = -d
    s = p @ d
    tc = t - t.mean()
    return float(tc @ s / (tc @ tc))


def measured_speed(markers: np.ndarray, fps: float = FPS) -> float:
    t = np.arange(len(markers)) / fps
    head = 0.5 * (markers[:, 0] + markers[:, 1])
    return line_speed(t, head, markers[:, 0] - markers[:, 1])


def tail_frequency(signal: np.ndarray, fps: float = FPS) -> float:
    """Dominant frequency of a lateral signal: FFT peak refined by a least-squares sinusoid scan."""
    x = signal - signal.mean()
    n = len(x)
    spec = np.abs(np.fft.rfft(x * np.hanning(n)))
    freqs = np.fft.rfftfreq(n, 1.0 / fps)
    spec[freqs < 0.1] = 0.0
    f0 = freqs[np.argmax(spec)]
    t = np.arange(n) / fps
    grid = np.linspace(max(0.05, f0 - 1.5 / (n / fps)), f0 + 1.5 / (n / fps), 601)
    power = []
    for f in grid:
        basis = np.stack([np.cos(2 * np.pi * f * t), np.sin(2 * np.pi * f * t), np.ones(n)], axis=1)
        coef, *_ = np.linalg.lstsq(basis, x, rcond=None)
        power.append(coef[0] ** 2 + coef[1] ** 2)
    return float(grid[int(np.argmax(power))])


def yaw_amplitude(markers: np.ndarray, freq: float, fps: float = FPS) -> float:
    """Amplitude of the head's heading angle (marker 1 -> marker 0) at the beat frequency: least
    squares of a line (slow turning) plus one sinusoid through the unwrapped angle."""
    e = markers[:, 0] - markers[:, 1]
    ang = np.unwrap(np.arctan2(e[:, 1], e[:, 0]))
    t = np.arange(len(ang)) / fps
    w = 2 * np.pi * freq
    basis = np.stack([np.ones_like(t), t, np.cos(w * t), np.sin(w * t)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, ang, rcond=None)
    return float(np.hypot(coef[2], coef[3]))


def tail_markers(local: np.ndarray, min_gap: float = TAIL_MARKER_MIN_GAP) -> list[int]:
    """Tail markers (2..8) that track distinct points: mean x increasing by >= min_gap.

    Some videos lose tail markers onto one point (label 2.25: markers 4-7 coincide); those
    would pin the wave fit to one spot several times over.
    """
    keep = [2]
    mean_x = local[:, :, 0].mean(axis=0)
    for i in range(3, N_MARKERS):
        if mean_x[i] - mean_x[keep[-1]] >= min_gap:
            keep.append(i)
    return keep


def _check_swaps(source: str, local: np.ndarray) -> None:
    """Tail markers keep their order along the body (the five clips: each next marker at least 1.5 mm further back
    along the head's axis in every frame, or, where two were lost onto one point, within 5 mm of it in median). A
    tracker that swaps two markers' identities mid-clip puts them in order for a stretch and reversed for another; the
    clip-mean order check cannot see a swap near the middle (the two means coincide, and the pair was merged as one
    point: the tail wave was fitted to a tail folding on itself)."""
    for i in range(2, N_MARKERS - 1):
        dx = local[:, i + 1, 0] - local[:, i, 0]
        if np.median(np.abs(dx)) < TAIL_MARKER_MIN_GAP:  # lost onto one point together (the 2.25 Hz clip's 4-7)
            continue
        behind = dx < -TAIL_MARKER_MIN_GAP
        runs = {side: max((n for _, n in true_runs(mask)), default=0) for side, mask in
                (("reversed", behind), ("in order", dx > TAIL_MARKER_MIN_GAP))}
        if min(runs.values()) >= MAX_SWAPPED_FRAMES:
            _swap_error(source, i, i + 1, behind)


def _swap_error(source: str, a: int, b: int, ahead: np.ndarray):
    raise InputError(source, f"tail markers {a} and {b}",
                     f"marker {b} lies ahead of marker {a} along the body in {int(ahead.sum())} of {len(ahead)} frames "
                     f"(first frame {int(np.argmax(ahead)) + 1}), behind it in the others: their identities swap "
                     "during the clip (or the body curls so far that they lie side by side)? give the tracks with "
                     "each marker's identity kept")


def _a_body_with_head_markers_exchanged(source: str, markers: np.ndarray) -> bool:
    """Whether exchanging head markers 0 and 1 gives this robot's body: tail markers one behind another, the tail
    base where the body has it (a file written x0..x8, y0..y8 gives neither either way)."""
    swapped = markers[:, [1, 0, *range(2, N_MARKERS)]]
    if len(tail_markers(head_frame(swapped))) < 3:
        return False
    try:
        _check_body(source, swapped)
    except InputError:
        return False
    return True


def _check_marker_order(source: str, markers: np.ndarray, keep: list[int]) -> None:
    """Head markers 0 and 1 sit on the rigid head, in front of the tail. Written tail first, markers 0-1 flex and 7-8
    keep their distance; with 0 and 1 exchanged, the tail lies on the far side of marker 0 from marker 1. Both had been
    refused as a tail-marker swap or as markers that do not lie one behind another, naming neither cause (review of
    stop 55)."""
    def flex(a: int, b: int) -> float:
        d = np.linalg.norm(markers[:, a] - markers[:, b], axis=1)
        return float(d.std() / max(d.mean(), 1e-300))

    head, tail = flex(0, 1), flex(N_MARKERS - 2, N_MARKERS - 1)
    if head > HEAD_FLEX and tail < head / 2:
        raise InputError(source, "marker order", f"head markers 0 and 1 flex ({100 * head:.1f} % scatter in their "
                         f"distance) while the last two keep theirs ({100 * tail:.1f} %): written tail first? write "
                         "x0, y0, ..., x8, y8 with the head's markers 0 and 1 first")
    if len(keep) < 3 and _a_body_with_head_markers_exchanged(source, markers):
        raise InputError(source, "markers 0 and 1", "the tail lies on the far side of marker 0 from marker 1: head "
                         "markers 0 and 1 exchanged? marker 0 is the head's front marker, marker 1 the one behind it")


def analyse(rate: Rate) -> Rate:
    """Fill tail_freq, speed and the head-frame tail markers (meta) of a rate."""
    local = head_frame(rate.markers)
    keep = tail_markers(local)
    _check_marker_order(rate.source or rate.name, rate.markers, keep)
    if len(keep) < 3:
        # also what a file written x0..x8, y0..y8 gives: its "markers" do not lie one behind another
        raise InputError(rate.source or rate.name, "tail markers",
                         f"only {len(keep)} of the tail markers 2-8 lie one behind another along the body (3 needed): "
                         "markers lost onto one point, or columns not written x0, y0, x1, y1, ..., x8, y8 (head "
                         "markers 0 and 1 first, tail last)")
    _check_swaps(rate.source or rate.name, local)
    mean_x = local[:, :, 0].mean(axis=0)
    ahead = [i for i in range(3, N_MARKERS) if mean_x[i] < mean_x[2:i].max() - TAIL_MARKER_MIN_GAP]
    if ahead:
        # markers lost onto one point lie together (label 2.25's 4-7), but one that lies clearly ahead of a marker
        # written before it is a column order error, and tail_markers would drop it in silence
        i = ahead[0]
        raise InputError(rate.source or rate.name, f"tail marker {i}",
                         f"lies {100 * (mean_x[2:i].max() - mean_x[i]):.1f} cm ahead of a marker written before it "
                         "along the body: tail markers 2-8 must be written head to tail")
    _check_body(rate.source or rate.name, rate.markers)
    expected = TAIL_BEAT_PER_LABEL * rate.label
    if expected > 0 and rate.fps / expected < MIN_FRAMES_PER_BEAT:
        # too few frames a beat alias the tail's wave to a slower one (every 30th frame read at 2 fps: 0.33 Hz where
        # the robot beats 1.69 Hz), which the length rule in seconds had let through (review of stop 59)
        raise InputError(rate.source or rate.name, "fps",
                         f"{rate.fps:g} frames per second give {rate.fps / expected:.1f} frames a tail beat (this "
                         f"robot beats at ~{expected:.3g} Hz at label {rate.label:g}): at least {MIN_FRAMES_PER_BEAT} "
                         "are needed to follow the tail's wave; give --fps if the clip was filmed at another rate")
    mended = _mend_tail_glitches(local, _resolution(rate.markers))
    rate.tail_freq = tail_frequency(local[:, keep[-1], 1], rate.fps)
    frames = len(rate.markers)
    if np.floor(frames / rate.fps * rate.tail_freq + 1e-6) < 1:  # the features are per complete beat
        # a clip that short gets a frequency from its trend, not from a beat (121 frames of the 1.00 Hz clip: 0.05 Hz)
        expected = TAIL_BEAT_PER_LABEL * rate.label
        if expected > 0 and frames / rate.fps * expected >= 2:  # long enough: the tail's signal has no clear beat
            raise InputError(rate.source or rate.name, f"marker {keep[-1]}",
                             f"no tail beat found: the tail's lateral motion in the head's frame gives "
                             f"{rate.tail_freq:.3f} Hz, no complete beat in {frames / rate.fps:.2f} s, where this "
                             f"robot beats at ~{expected:.3g} Hz (a sharp turn, a tail not tracked, the wrong label?)")
        need = (f"; this robot beats at ~{expected:.3g} Hz here: give at least two beats, "
                f"{int(np.ceil(2 * rate.fps / expected))} frames") if expected > 0 else ""
        raise InputError(rate.source or rate.name, "rows",
                         f"{frames} frames ({frames / rate.fps:.2f} s at {rate.fps:g} fps) are too short to measure "
                         f"the tail beat (the estimate, {rate.tail_freq:.3f} Hz, holds no complete beat){need}")
    rate.speed = measured_speed(rate.markers, rate.fps)
    head = 0.5 * (rate.markers[:, 0] + rate.markers[:, 1])
    travel = float(np.linalg.norm(head[-1] - head[0]))
    # a swimming fish travels head first: a track that stays put or goes tail first is not a swim to fit
    if not (rate.speed > MIN_SPEED and travel > MIN_TRAVEL):
        raise InputError(rate.source or rate.name, "markers",
                         f"the head does not move forward (speed {rate.speed:.4f} m/s along the heading, "
                         f"{travel:.3f} m from start to end): a swimming clip moves head first")
    rate.yaw_amp = yaw_amplitude(rate.markers, rate.tail_freq, rate.fps)
    _check_tail_jumps(rate.source or rate.name, local)
    rate.meta = {"local": local, "tail_markers": keep, "mended": mended}
    rate.meta["flags"] = clip_flags(rate)
    rate.meta["feature_flags"] = feature_flags(rate)
    return rate


def _mend_tail_glitches(local: np.ndarray, grid: float = 0.0) -> list[tuple[int, int, int, float]]:
    """A tail marker that jumps more than MAX_TAIL_JUMP x its steps either side and comes back within 3 frames is a
    tracking glitch: those samples are read as the line between the frames either side, in the head frame the tail
    wave is fitted in (mended in place; returned as (marker, first, frames, ratio)). Kept, one glitch of one marker
    in one frame had moved Kutta lift -3 stds and put the tail tip's amplitude at 0.68 m on a 0.55 m fish, in silence
    (a probe of stop 58). grid: the file's number grid (m); a jump of a few grid steps is no glitch however still the
    marker is otherwise (240 fps with 0.1 px of noise on a 1 px grid: one step 10-39 x the median)."""
    mended = []
    for i in range(2, N_MARKERS):
        p = local[:, i]
        for _ in range(8):  # a few glitches per marker; more is a track, not glitches
            frame, ratio = largest_jump_on_both_sides(np.linalg.norm(np.diff(p, axis=0), axis=1))
            if ratio <= MAX_TAIL_JUMP:
                break
            step = np.linalg.norm(p[frame + 1] - p[frame])
            if step <= GLITCH_GRID_STEPS * grid:
                break  # a flicker on the file's number grid of a marker nearly at rest, no glitch
            # the jump out (the marker is back at frame k) or the jump back (it had left after frame k)
            out = [(frame, k) for k in range(frame + 2, min(frame + 5, len(p)))
                   if np.linalg.norm(p[k] - p[frame]) < 0.5 * step]
            back = [(k, frame + 1) for k in range(frame - 1, max(frame - 4, -1), -1)
                    if np.linalg.norm(p[k] - p[frame + 1]) < 0.5 * step]
            if not out + back:
                break  # no glitch: a seam, which _check_tail_jumps judges
            a, b = (out + back)[0]
            w = (np.arange(1, b - a) / (b - a))[:, None]
            p[a + 1:b] = (1 - w) * p[a] + w * p[b]
            mended.append((i, a + 1, b - a - 1, float(ratio)))
    return mended


def _check_tail_jumps(source: str, local: np.ndarray) -> None:
    """Two takes joined with the head's track made continuous leave no jump of the head, but the tail's phase jumps
    at the seam, for every tail marker at once (the tail-beat frequency moved 9 %, Magnus lift 40x, in silence). A
    tracking glitch moves one marker, for a frame or a few, and is no seam."""
    big = []
    for i in range(2, N_MARKERS):
        p = local[:, i]
        frame, ratio = largest_jump_on_both_sides(np.linalg.norm(np.diff(p, axis=0), axis=1))
        if ratio <= MAX_TAIL_JUMP:
            continue
        step = np.linalg.norm(p[frame + 1] - p[frame])
        returns = [np.linalg.norm(p[k] - p[frame]) < 0.5 * step for k in range(frame + 2, min(frame + 5, len(p)))]
        if not any(returns):  # a marker that jumps and comes back within 3 frames is a glitch (or two swapped briefly)
            big.append((i, frame, ratio))
    for _, frame, _ in big:
        group = [(j, r) for j, f, r in big if abs(f - frame) <= 1]
        if len(group) >= 2:
            raise InputError(source, f"tail markers {', '.join(str(j) for j, _ in group)}",
                             f"jump together, up to {max(r for _, r in group):.0f} x their frame-to-frame steps on "
                             f"either side, in the head's frame, between frames {frame + 1} and {frame + 2}: two takes "
                             "joined, or frames missing? give one continuous take")


def beat_windows(t: np.ndarray, freq: float) -> list[np.ndarray]:
    """Index arrays of the complete beats of the clock (beat b: t in [b/f, (b+1)/f)), t from 0."""
    period = 1.0 / freq
    dt = float(np.median(np.diff(t)))
    n = int(np.floor((t[-1] + dt) / period + 1e-6))
    eps = 1e-6 * dt
    return [np.nonzero((t >= b * period - eps) & (t < (b + 1) * period - eps))[0] for b in range(n)]


def beat_speeds(rate: Rate) -> np.ndarray:
    """The forward speed over each complete tail beat of a clip: the features' per-beat speed (the slope of the head's
    progress along the clip's swimming direction, fitted with the beat's harmonics). A straight line fitted along
    each beat's own principal axis, as here until stop 48, read the sideways sway of a slow beat as its axis: the
    0.75 Hz clip of fishsim's repository, which the shipped data lacks, cruises at 0.042 and 0.043 m/s and was
    flagged as not cruising at 0.003 and 0.010 m/s."""
    from wrenorm.tasks.swimmer.features import real_features  # features imports this module

    return np.asarray(real_features(rate)[2]["speed"], np.float64)


def clip_flags(rate: Rate) -> list[str]:
    """What the clip's own motion says it is not: a steady straight swim filmed at one scale with a tracker of the
    fishsim clips' precision. Said, not refused (a held-out clip so flagged does not decide the verdict)."""
    name, flags = rate.source or rate.name, []
    speeds = beat_speeds(rate)
    if len(speeds) >= 2 and np.median(speeds) > 0:
        change = np.abs(speeds / np.median(speeds) - 1.0)
        if change.max() > MAX_BEAT_SPEED_CHANGE:
            k = int(np.argmax(change))
            flags.append(f"{name}: beat {k + 1} of {len(speeds)} swims {speeds[k]:.3f} m/s against the clip's median "
                         f"beat {np.median(speeds):.3f} m/s: the fish is not cruising (starting, stopping?); the fit "
                         "takes the clip's speed as a cruising speed: cut the clip to its steady part")
    copies = sum(n for _, n in moving_repeats(rate.markers))
    if copies:
        flags.append(f"{name}: {copies} of {len(rate.markers)} frames repeat the previous frame exactly while the fish "
                     "swims (duplicated frames? tracked video never repeats): each copy slows the speed and the tail "
                     f"beat by its share; {100 * MAX_REPEATED_FRAMES:.0f} % or more is refused")
    if rate.frame != "world":
        return flags
    e = rate.markers[:, 0] - rate.markers[:, 1]
    heading = np.unwrap(np.arctan2(e[:, 1], e[:, 0]))
    per = max(1, int(round(rate.fps / rate.tail_freq)))
    if len(heading) > per:
        turn = float(np.degrees(np.ptp(np.convolve(heading, np.ones(per) / per, mode="valid"))))
        if turn > MAX_TURN_DEG:
            flags.append(f"{name}: the fish turns {turn:.0f} deg over the clip (beat-averaged heading): the model "
                         "swims straight, and the speed and head-motion features are read as from a straight swim")
    dist = np.linalg.norm(e, axis=1)
    third = len(dist) // 3
    drift = float(np.mean(dist[-third:]) / np.mean(dist[:third]) - 1.0)
    if abs(drift) > MAX_HEAD_DRIFT:
        flags.append(f"{name}: the head markers' pixel distance changes {100 * drift:+.0f} % from the first third of "
                     "the clip to the last: the pixel scale changes along the path (a camera not square to the "
                     "water?), and one scale is used for the whole clip")
    return flags


def feature_flags(rate: Rate) -> list[str]:
    """What the clip's tracking says of its head-motion features alone, which the speed (the held-out verdict's
    observable, a slope over the whole clip) does not share: one marker held or interpolated for a stretch, tracking
    noise. Said, and a held-out clip so flagged still decides (1.5 px of noise on the held-out clip alone had left its
    speed 0.2213 m/s for 0.2214 and turned the verdict from "expand" to "absorbed" by dropping it; a probe of stop
    58)."""
    name, flags = rate.source or rate.name, []
    which = range(N_MARKERS) if rate.frame == "world" else range(1, N_MARKERS)  # a head frame's origin is marker 0
    lines = straight_runs(rate.markers, which)
    for first, n, _ in (r for r in lines if len(r[2]) > 1):  # shorter than refused
        flags.append(f"{name}: every marker moves on a straight line at constant speed for {n} frames "
                     f"({first + 1}-{first + n}) while the fish swims: a fill by interpolation? (the fishsim clips: "
                     f"none; {REFUSED_FILL_FRAMES} frames or more are refused); rounded to a coarse grid, a tracked "
                     "clip may do so for a few frames by itself")
    for first, n in cubic_runs(rate.markers, which):
        flags.append(f"{name}: every marker lies on one cubic in time for {n} frames ({first + 1}-{first + n}) "
                     "while the fish swims (the fishsim clips: never): a spline's fill of lost frames? it erases the "
                     "head's sway and surge within the beat (20 frames so filled twice: blunt drag -3.4 stds); give "
                     "the tracked frames, or cut the clip there; rounded to a coarse grid, a tracked clip may do so "
                     "for a few frames by itself")
    for first, n in held_edges(rate.markers):
        where = "start" if first == 0 else "end"
        flags.append(f"{name}: frames {first + 1}-{first + n} at the clip's {where} are one frame repeated exactly: "
                     "a lost stretch filled with the first or last position (bfill / ffill)? cut them (12 such frames "
                     "at both ends: blunt drag -1.65 stds)")
    runs = [r for r in lines if len(r[2]) == 1]
    for m in dict.fromkeys(r[2][0] for r in runs):  # one line per marker
        mine = [(first, n) for first, n, (k,) in runs if k == m]
        where = ", ".join(f"{first + 1}-{first + n}" for first, n in mine)
        flags.append(f"{name}: marker {m} moves on a straight line at constant speed (or stands still) for "
                     f"{max(n for _, n in mine)} frames in a row (frames {where}) while the fish swims (the fishsim "
                     "clips: at most 6): held or interpolated by a tracker? its motion within the beat is gone there, "
                     "and the fitted coefficients move with it (one head marker held 10 frames: blunt drag -3.6 stds); "
                     f"or a marker this slow on the file's number grid ({1000 * _resolution(rate.markers):.2g} mm "
                     "here; the fishsim clips': 0.5 mm) does so by itself")
    for m, first, n, ratio in rate.meta.get("mended", []):
        where = f"frame {first + 1}" if n == 1 else f"frames {first + 1}-{first + n}"
        flags.append(f"{name}: tail marker {m} jumps {ratio:.0f} x its steps either side and comes back ({where}): a "
                     "tracking glitch, read as the line between the frames either side")
    if rate.frame != "world":
        return flags
    dist = np.linalg.norm(rate.markers[:, 0] - rate.markers[:, 1], axis=1)
    scatter = float(np.std(np.diff(dist, 2)) / np.mean(dist))
    if scatter > MAX_HEAD_SCATTER:
        flags.append(f"{name}: the rigid head markers' distance scatters {1000 * scatter:.0f} per mille from frame "
                     "to frame (tracking noise; the fishsim clips: 11-14): the head-motion features are noisier than "
                     "the fit's noise model holds (the speed, a slope over the clip, is not)")
    return flags


# --- built-in data -----------------------------------------------------------------------------

def _data_dir() -> Path:
    from wrenorm import data
    return Path(data.__file__).parent


def load_builtin() -> list[Rate]:
    """The five recorded rates shipped in wrenorm/data (metres, world frame)."""
    path = _data_dir() / BUILTIN
    with np.load(path, allow_pickle=False) as z:
        labels = z["labels"]
        rates = []
        for lab in labels:
            key = f"{lab:.2f}"
            rates.append(analyse(Rate(label=float(lab), markers=z[f"markers_{key}"].astype(np.float64),
                                      source=f"{BUILTIN}:{key}", fps=float(z["fps"]))))
    return rates


def write_builtin(src_dir, out_path=None) -> Path:
    """Regenerate wrenorm/data/fishsim_kinematics.npz from a folder of fishsim CSVs.

    Stores each rate's marker tracks in metres (float32) plus the derived tail-beat frequency and
    speed for reference; the task re-derives everything from the tracks when it loads them.
    """
    rates = load_dir(src_dir)
    out_path = Path(out_path) if out_path else _data_dir() / BUILTIN
    arrays = {"labels": np.array([r.label for r in rates]), "fps": np.array(FPS),
              "tail_freq": np.array([r.tail_freq for r in rates]),
              "speed": np.array([r.speed for r in rates]),
              "provenance": np.array(
                  "Marker tracks of the tendon-driven robotic fish, Michelis, Obayashi, Hughes, Katzschmann, "
                  "'Simple Models, Real Swimming' (arXiv 2602.23283), repository srl-ethz/fishsim, MIT licence "
                  "(LICENSE_fishsim). Converted from markers_f*.csv pixels to metres with the 0.142 m head-marker "
                  "distance by wrenorm.tasks.swimmer.data.write_builtin.")}
    for r in rates:
        arrays[f"markers_{r.label:.2f}"] = r.markers.astype(np.float32)
    np.savez_compressed(out_path, **arrays)
    return out_path


if __name__ == "__main__":
    import sys

    print(write_builtin(sys.argv[1] if len(sys.argv) > 1 else "/work/shared/data/fishsim/markers"))
