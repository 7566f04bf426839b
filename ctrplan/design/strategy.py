"""A CMA-ES (the ``cma`` package) that draws only from its own random state.

``cma`` samples with ``numpy.random`` (the global generator) and seeds it when it starts. Every
call into it here runs with the strategy's own generator state swapped in, and the caller's
state put back afterwards, so the candidates depend only on the seed and the fitness values
told (not on whatever else in this process used numpy's global generator in between: the
planner seeds it for every plan).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator

import numpy as np


class Strategy:
    """CMA-ES over the unit cube [0, 1]^dim for designs of ``k`` tubes.

    popsize : candidates per generation. seed : the strategy's seed (restarts derive theirs
    from it). x0 (dim,), sigma0 : the start.
    """

    def __init__(self, k: int, dim: int, popsize: int, seed: int, x0: np.ndarray, sigma0: float = 0.3):
        self.k = int(k)
        self.dim = int(dim)
        self.popsize = int(popsize)
        self.seed = int(seed)
        self.restarts = 0
        self._state = None
        self._start(np.asarray(x0, float), sigma0)

    @contextlib.contextmanager
    def _own_random(self) -> Iterator[None]:
        caller = np.random.get_state()
        try:
            if self._state is not None:
                np.random.set_state(self._state)
            yield
            self._state = np.random.get_state()
        finally:
            np.random.set_state(caller)

    def _start(self, x0: np.ndarray, sigma0: float) -> None:
        import cma

        opts = {"bounds": [0.0, 1.0], "popsize": self.popsize, "seed": self.seed * 1009 + self.restarts + 1,
                "verbose": -9, "verb_disp": 0, "verb_log": 0, "tolflatfitness": 3,
                "CMA_mirrors": 0}
        self._state = None
        with self._own_random(), contextlib.redirect_stdout(io.StringIO()):
            self.es = cma.CMAEvolutionStrategy(np.clip(x0, 0.02, 0.98).tolist(), sigma0, opts)

    def ask(self) -> list[np.ndarray]:
        """``popsize`` candidates (each (dim,) in [0, 1])."""
        with self._own_random():
            xs = self.es.ask()
        return [np.clip(np.asarray(x, float), 0.0, 1.0) for x in xs]

    def tell(self, xs: list[np.ndarray], fitness: list[float], best_x: np.ndarray | None = None) -> None:
        """Fitness (smaller is better) of the candidates asked; a strategy that stops restarts
        around ``best_x`` (or the centre) with a smaller step."""
        with self._own_random(), contextlib.redirect_stdout(io.StringIO()):
            self.es.tell([list(x) for x in xs], [float(f) for f in fitness])
            stop = bool(self.es.stop())
        if stop:
            self.restarts += 1
            x0 = best_x if best_x is not None else np.full(self.dim, 0.5)
            self._start(np.asarray(x0, float), 0.2)

    @property
    def sigma(self) -> float:
        return float(self.es.sigma)
