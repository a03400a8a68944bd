"""Warm starts: a CMA-ES search distribution of one structure (`Search`) and a child's
search inherited from its parent's (`inherited`, genes matched by `align`)."""

from __future__ import annotations

import difflib
import math
from typing import Any, NamedTuple

import numpy as np

from .genome import Genome

__all__ = ["Search", "align", "inherited"]


class Search(NamedTuple):
    """A CMA-ES search distribution of one structure, in its genome's parameter order: a
    warm start for `tune` and what `tune` hands back (``Tuned.searches``).

    Attributes:
      sigma: the step size.
      cov: ``[n, n]`` covariance matrix C (symmetric, positive definite), ``n`` the genome's
        number of parameters; the search is ``N(weights, sigma^2 C)``.
    """

    sigma: float
    cov: np.ndarray

    def check(self, n: int, what: str) -> None:
        """Raise one ValueError naming ``what`` unless this is a search of ``n`` parameters."""
        cov = np.asarray(self.cov)
        if not (isinstance(self.sigma, int | float) and math.isfinite(self.sigma)
                and self.sigma > 0):  # fmt: skip
            raise ValueError(f"{what}: sigma must be a finite number > 0, got {self.sigma!r:.40}")
        if cov.shape != (n, n) or not np.all(np.isfinite(cov)):
            raise ValueError(
                f"{what}: cov must be a finite {n} x {n} matrix (one row per parameter of its "
                f"genome), got shape {cov.shape}"
            )
        if not np.allclose(cov, cov.T, rtol=1e-5, atol=1e-12 * max(1.0, np.abs(cov).max())):
            raise ValueError(f"{what}: cov is not symmetric")

    def to_json(self) -> dict:
        return {"sigma": float(self.sigma), "cov": np.asarray(self.cov, np.float64).tolist()}

    @classmethod
    def from_json(cls, d: Any, n: int, what: str) -> Search:
        """`to_json`'s dict of a search of ``n`` parameters; one ValueError if it is not."""
        if not isinstance(d, dict) or set(d) != {"sigma", "cov"}:
            raise ValueError(f"{what}: a search is an object with sigma and cov")
        try:
            cov = np.asarray(d["cov"], np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{what}: cov is not a matrix of numbers") from None
        sigma = d["sigma"]
        out = cls(float(sigma) if isinstance(sigma, int | float) else sigma, cov)
        out.check(n, what)
        return out


def inherited(parent: Genome, search: Search, child: Genome, sigma0: float) -> Search:
    """A child's warm start from its parent's final search: the parent's covariance on the
    genes the child kept, the identity on its new genes, step size ``sigma0``.

    The parent's C is scaled to a mean eigenvalue of 1 (trace n): its shape, the
    correlations and relative scales the parent learned, is inherited, not the scale at which
    the parent's search converged (``sigma`` carries that, and a converged ``sigma`` would
    leave the new genes, which join at weight 0, no room to move). Genes are matched by
    aligning the two gene lists (`align`)."""
    match = align(parent, child)
    cov = np.asarray(search.cov, np.float64)
    n_p, trace = cov.shape[0], np.trace(cov)
    scale = n_p / trace if n_p and trace > 0 else 1.0
    n = child.n_params
    out = np.eye(n)
    kept = [j for j in range(n) if match[j] is not None]
    src = [match[j] for j in kept]
    out[np.ix_(kept, kept)] = cov[np.ix_(src, src)] * scale
    return Search(float(sigma0), out)


def align(parent: Genome, child: Genome) -> list[int | None]:
    """For each gene of ``child``, the index of the same gene in ``parent`` (None: new).

    Structural mutation inserts and deletes genes but never reorders them, and copies the
    genes it keeps with their weights; so the genes that two genomes share are the longest
    common subsequence of their ``(kind, ref, weight)`` lists (a neuron gene's arity may
    differ: a connection was added to or removed from it)."""

    def sig(g: Genome):
        return [(gene.kind, gene.ref, float(gene.weight)) for gene in g.genes]

    out: list[int | None] = [None] * len(child.genes)
    sm = difflib.SequenceMatcher(None, sig(parent), sig(child), autojunk=False)
    for block in sm.get_matching_blocks():
        for k in range(block.size):
            out[block.b + k] = block.a + k
    return out
