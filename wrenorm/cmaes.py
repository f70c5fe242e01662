"""The engine's one CMA-ES: several pycma searches over one box, asked and told together, so that every
generation of every search is ONE batched evaluation (thousands of coarse models per launch).

A fit runs one search (or several seeded ones side by side on a wide device), identifiability restarts
and flows run several, the rope planner runs several over commands instead of parameters: all through
this class. Each search draws its samples from its own seeded generator, so it repeats exactly whatever
else the process does with numpy's global random state.

Resuming is a replay, not unpickling: the state is the list of losses told to each search per generation
(plain numbers), plus a digest of each generation's candidates. A fresh instance with the same settings
asks again, checks that it proposes the very same candidates, and is told the stored losses; pycma is
deterministic, so the replayed search is bit-identical to the interrupted one, and a state that belongs
to other settings (or was edited) is refused.
"""
from __future__ import annotations

import hashlib
import sys
import warnings
from dataclasses import dataclass

import numpy as np

from wrenorm.errors import InputError

BLOWUP_LOSS = 1e30  # pycma ranks candidates, so a blown-up candidate only has to rank last
STATE_SCHEMA = "wrenorm.cmaes-state/1"
# pycma imports these for optional extras (plots, a surrogate's rank statistics) inside try/except ImportError;
# they cost 2 s of every fit's start-up and the searches use neither
_CMA_OPTIONAL = ("matplotlib", "matplotlib.pyplot", "scipy.stats")


def import_cma():
    """pycma, imported without its optional plotting and statistics dependencies (seen as absent while it
    imports, so it takes its own fallbacks); later imports of those modules elsewhere are unaffected."""
    if "cma" in sys.modules:
        return sys.modules["cma"]
    blocked = [m for m in _CMA_OPTIONAL if m not in sys.modules]
    for m in blocked:
        sys.modules[m] = None  # an import of a None entry raises ImportError
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import cma
    finally:
        for m in blocked:
            if sys.modules.get(m, 0) is None:
                del sys.modules[m]
    return cma


@dataclass
class Search:
    """One search's record: its best point, and what it cost."""

    seed: int
    best_x: np.ndarray
    best_loss: float = np.inf
    evaluations: int = 0
    blowups: int = 0
    generations: int = 0
    stop: str = ""
    failed: bool = False  # a whole generation blew up: the search stopped there


def _bounded(tf, Y: np.ndarray) -> np.ndarray:
    """pycma's linear-quadratic box transformation (`BoxConstraintsLinQuadTransformation.__call__`) on every row of
    Y at once: the same element-wise steps in the same order, so bit-identical to pycma's row-by-row call (tested),
    which costs ~40 us a row in numpy call overhead (2.8 s of a 32-search rope fit on an H100)."""
    if len(tf._lb) != Y.shape[1]:
        tf.initialize(Y.shape[1])
    lb, ub, al, au = (np.broadcast_to(a, Y.shape) for a in (tf._lb, tf._ub, tf._al, tf._au))
    y = np.array(Y, dtype=float)
    idx = (y < lb - 2 * al - (ub - lb) / 2.0) | (y > ub + 2 * au + (ub - lb) / 2.0)
    if idx.any():
        r = 2 * (ub[idx] - lb[idx] + al[idx] + au[idx])
        start = lb[idx] - 2 * al[idx] - (ub[idx] - lb[idx]) / 2.0
        y[idx] -= r * ((y[idx] - start) // r)
    idx = y > ub + au
    y[idx] -= 2 * (y[idx] - ub[idx] - au[idx])
    idx = y < lb - al
    y[idx] += 2 * (lb[idx] - al[idx] - y[idx])
    idx = y < lb + al
    y[idx] = lb[idx] + (y[idx] - (lb[idx] - al[idx])) ** 2 / 4 / al[idx]
    idx = y > ub - au
    y[idx] = ub[idx] - (y[idx] - (ub[idx] + au[idx])) ** 2 / 4 / au[idx]
    return y


def _ask(es) -> np.ndarray:
    """es.ask() with the bound transform applied to the whole population at once. pycma's ask is: sample genotypes,
    map each into the box, remember each phenotype's genotype for `tell`; this does the same steps, and falls back
    to es.ask() where the search is set up otherwise than BatchedCMAES sets it (a coordinate transformation, another
    boundary handler, integer variables), on a pycma other than 4.x (written against 4.5), or where an attribute it
    uses is missing."""
    handler = getattr(es, "boundary_handler", None)
    tf = getattr(handler, "bounds_tf", None)
    countiter = getattr(es, "countiter", None)
    if not (str(getattr(import_cma(), "__version__", "")).startswith("4.")
            and getattr(getattr(es, "gp", None), "isidentity", False)
            and all(hasattr(tf, a) for a in ("_lb", "_ub", "_al", "_au", "initialize"))
            and not (getattr(es, "opts", None) or {}).get("integer_variables")
            and hasattr(es, "sent_solutions") and hasattr(es, "ask_geno")
            and isinstance(countiter, int) and (countiter == 0 or hasattr(es, "timer"))):
        return np.asarray(es.ask())
    if es.countiter == 0:
        es.timer = import_cma().utilities.utils.ElapsedWCTime()
    else:
        _ = es.timer.tic  # a property that restarts pycma's clock, as its ask does
    geno = es.ask_geno()
    pheno = _bounded(tf, np.asarray(geno))
    for g, x in zip(geno, pheno):
        es.sent_solutions.insert(x, geno=g, iteration=es.countiter)
    return pheno


def _digest(x: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(x, dtype=np.float64).tobytes()).hexdigest()[:16]


class BatchedCMAES:
    """K seeded CMA-ES searches in the box [lower, upper].

    x0s (K, F) start points, sigma0 the initial step (a scalar, in the box's units), seeds one per search.
    `ask()` returns the candidates of every active search stacked (N, F); `tell(losses)` takes their
    losses (N,) in the same order (non-finite = blew up). A search stops at `max_generations`, at pycma's
    own criteria, or when a whole generation of it blows up.
    """

    def __init__(self, x0s, sigma0: float, lower, upper, seeds, popsize: int | None = None,
                 max_generations: int = 100, tolfun: float = 1e-12, tolx: float = 1e-10):
        cma = import_cma()

        x0s = np.atleast_2d(np.asarray(x0s, dtype=np.float64))
        self.dim = x0s.shape[1]
        self.lower = np.broadcast_to(np.asarray(lower, np.float64), (self.dim,)).copy()
        self.upper = np.broadcast_to(np.asarray(upper, np.float64), (self.dim,)).copy()
        if self.dim < 1 or not np.all(self.upper > self.lower):
            raise ValueError(f"need a box with upper > lower in every coordinate, got {self.lower}, {self.upper}")
        seeds = [int(s) for s in seeds]
        if len(seeds) != len(x0s):
            raise ValueError(f"{len(x0s)} start points but {len(seeds)} seeds")
        self.max_generations = int(max_generations)
        # pycma needs at least two coordinates: a lone parameter gets a dummy partner it never sees
        self._pad = self.dim == 1
        lo, hi = self.lower, self.upper
        if self._pad:
            lo, hi = np.append(lo, 0.0), np.append(hi, 1.0)
        span = hi - lo
        self.es, self.searches, self._told = [], [], []
        for x0, seed in zip(x0s, seeds):
            x0 = np.clip(x0, self.lower, self.upper)
            start = np.clip(np.append(x0, 0.5) if self._pad else x0, lo + 1e-6 * span, hi - 1e-6 * span)
            rng = np.random.default_rng(seed)
            opts = {"bounds": [lo.tolist(), hi.tolist()], "maxiter": self.max_generations, "tolfun": tolfun,
                    "tolx": tolx, "verbose": -9, "randn": lambda *shape, rng=rng: rng.standard_normal(shape)}
            if popsize:
                opts["popsize"] = int(popsize)
            self.es.append(cma.CMAEvolutionStrategy(start, float(sigma0), opts))
            self.searches.append(Search(seed, x0.copy()))
            self._told.append([])
        self._asked: list[tuple[int, np.ndarray]] = []
        self.last_told: list[tuple[int, str, list]] = []  # (search, candidates' digest, losses) of the last tell

    # ------------------------------------------------------------------ loop
    @property
    def active(self) -> list[int]:
        return [k for k, (es, s) in enumerate(zip(self.es, self.searches))
                if not s.failed and s.generations < self.max_generations and not es.stop()]

    @property
    def done(self) -> bool:
        return not self.active

    @property
    def generation(self) -> int:
        return max(s.generations for s in self.searches)

    def ask(self) -> np.ndarray:
        self._asked = [(k, _ask(self.es[k])) for k in self.active]
        if not self._asked:
            return np.zeros((0, self.dim))
        return np.concatenate([X[:, :self.dim] for _, X in self._asked])

    @property
    def owners(self) -> np.ndarray:
        """(N,) which search each row of the last `ask()` belongs to."""
        return np.concatenate([np.full(len(X), k) for k, X in self._asked]) if self._asked else np.zeros(0, int)

    def tell(self, losses) -> None:
        losses = np.asarray(losses, dtype=np.float64).reshape(-1)
        n = sum(len(X) for _, X in self._asked)
        if len(losses) != n:
            raise ValueError(f"told {len(losses)} losses for {n} candidates")
        o = 0
        for k, X in self._asked:
            li = losses[o:o + len(X)]
            o += len(X)
            self._tell_one(k, X, li)
        self.last_told = [(k, *self._told[k][-1]) for k, _ in self._asked]
        self._asked = []

    def _tell_one(self, k: int, X: np.ndarray, losses: np.ndarray) -> None:
        s = self.searches[k]
        failed = ~np.isfinite(losses)
        s.evaluations += len(losses)
        s.blowups += int(failed.sum())
        told = np.where(failed, BLOWUP_LOSS, losses)
        self._told[k].append((_digest(X), [None if f else float(v) for f, v in zip(failed, losses)]))
        s.generations += 1
        if failed.all():
            s.failed, s.stop = True, f"every one of {len(losses)} candidates blew up at generation {s.generations - 1}"
            return
        self.es[k].tell(list(X), list(told))
        i = int(np.argmin(np.where(failed, np.inf, losses)))
        if losses[i] < s.best_loss:
            s.best_loss, s.best_x = float(losses[i]), X[i, :self.dim].copy()

    def finish(self) -> list[Search]:
        """Stop reasons filled in; the searches' records."""
        for es, s in zip(self.es, self.searches):
            if not s.stop:
                s.stop = ", ".join(es.stop()) or ("generations" if s.generations >= self.max_generations else "")
        return self.searches

    def sigma(self, k: int) -> float:
        return float(self.es[k].sigma)

    # ------------------------------------------------------------------ plain-format state
    @property
    def seeds(self) -> list[int]:
        return [s.seed for s in self.searches]

    def state(self) -> dict:
        """Everything needed to continue bit-identically, as plain JSON-able data."""
        return {"schema": STATE_SCHEMA, "seeds": self.seeds,
                "told": [[{"candidates": d, "losses": li} for d, li in told] for told in self._told]}

    def replay(self, state: dict, source: str = "search state") -> None:
        """Continue from `state` (see `state`): ask again, check the candidates, tell the stored losses."""
        try:
            if state.get("schema") != STATE_SCHEMA:
                raise ValueError(f"schema {state.get('schema')!r}, expected {STATE_SCHEMA!r}")
            seeds, told = [int(s) for s in state["seeds"]], state["told"]
            if seeds != [s.seed for s in self.searches] or len(told) != len(self.searches):
                raise ValueError("it was made by searches with other seeds")
            rows = [[(str(g["candidates"]), [np.nan if x is None else float(x) for x in g["losses"]]) for g in t]
                    for t in told]
        except (AttributeError, KeyError, TypeError, ValueError) as e:
            raise InputError(source, "state", f"is not a wrenorm search state of this run ({e})") from None
        gen = 0
        while any(gen < len(r) for r in rows):
            X = self.ask()
            losses = []
            for k, Xk in self._asked:
                if gen >= len(rows[k]):
                    raise InputError(source, "state", f"search {k} stops at generation {gen} in the state but not "
                                                      "here: the state belongs to other settings")
                digest, li = rows[k][gen]
                if digest != _digest(Xk) or len(li) != len(Xk):
                    raise InputError(source, "state", f"generation {gen} of search {k} proposes other candidates than "
                                                      "the state records: it belongs to other settings or was edited")
                losses += li
            if X.shape[0] == 0:
                raise InputError(source, "state", f"records more generations than these searches run ({gen})")
            self.tell(np.array(losses))
            gen += 1
