"""Affinity propagation on a sparse similarity (Frey and Dueck 2007, their sparse form).

scikit-learn's ``AffinityPropagation`` takes a dense (K, K) similarity and updates all K^2
messages every iteration. The super-pixel paper builds its similarity from adjacent
super-pixels only, so a row of terraced houses (thousands of hypotheses, a handful of
neighbours each) has a few thousand pairs, not millions: here the messages live on those
pairs alone, and an iteration costs O(pairs). On a complete graph the updates, the damping
and the stopping rule are scikit-learn's, and so are the exemplars.
"""

from __future__ import annotations

import numpy as np


def sparse_affinity_propagation(
    rows: np.ndarray,
    cols: np.ndarray,
    similarity: np.ndarray,
    n: int,
    preference: float,
    *,
    damping: float = 0.7,
    max_iter: int = 400,
    convergence_iter: int = 15,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Exemplars of ``n`` items from similarities on some of their pairs.

    Parameters
    ----------
    rows, cols : (E,) int
        Pairs (i, k): how well k would stand for i. Pairs absent are never chosen (as if
        their similarity were minus infinity). Self pairs are ignored: every item has
        ``preference`` as its own.
    similarity : (E,) float
        s(i, k), larger is more similar.
    n : int
        Number of items.
    preference : float
        s(k, k) of every item: how readily it becomes an exemplar.
    damping, max_iter, convergence_iter : as scikit-learn's ``AffinityPropagation``.
    seed : int
        Seed of the tiny noise that breaks ties between equal similarities (as
        scikit-learn adds).

    Returns
    -------
    exemplars : (P,) int, sorted
    assignment : (n,) int index into ``exemplars`` of each item's exemplar, -1 for an item
        with no pair to any exemplar.

    A run that has not settled after ``max_iter`` iterations returns the exemplars of its
    last one (scikit-learn returns none).
    """
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    off = rows != cols
    paired = np.bincount(rows[off], minlength=n) > 0
    if not paired.all():  # an item with no pair can only stand for itself
        index = np.cumsum(paired) - 1
        keep = off & paired[rows] & paired[cols]
        ex, _ = sparse_affinity_propagation(
            index[rows[keep]], index[cols[keep]], np.asarray(similarity)[keep],
            int(paired.sum()), preference, damping=damping, max_iter=max_iter,
            convergence_iter=convergence_iter, seed=seed,
        )  # fmt: skip
        exemplars = np.sort(np.concatenate([np.flatnonzero(paired)[ex], np.flatnonzero(~paired)]))
        s_all = np.concatenate([np.asarray(similarity, float)[off], np.zeros(n)])
        every = np.arange(n)
        return exemplars, _assign(
            np.concatenate([rows[off], every]), np.concatenate([cols[off], every]), s_all,
            exemplars, n,
        )  # fmt: skip
    rows = np.concatenate([rows[off], np.arange(n)])
    cols = np.concatenate([cols[off], np.arange(n)])
    s = np.concatenate([np.asarray(similarity, np.float64)[off], np.full(n, float(preference))])
    order = np.lexsort((cols, rows))
    rows, cols, s = rows[order], cols[order], s[order]
    rng = np.random.default_rng(seed)
    s = s + (np.finfo(float).eps * s + np.finfo(float).tiny * 100) * rng.standard_normal(len(s))
    starts = np.searchsorted(rows, np.arange(n))
    is_self = rows == cols
    self_at = np.flatnonzero(is_self)  # one per item, in item order
    R = np.zeros(len(s))
    A = np.zeros(len(s))
    history = np.zeros((n, convergence_iter), bool)
    for it in range(max_iter):
        # responsibility: r(i,k) = s(i,k) - max over k' != k of (a(i,k') + s(i,k'))
        AS = A + s
        first = np.maximum.reduceat(AS, starts)
        at_first = AS == first[rows]
        # the first position of each row's maximum; the others compete with it
        pos = np.where(at_first, np.arange(len(s)), len(s))
        arg = np.minimum.reduceat(pos, starts)
        masked = AS.copy()
        masked[arg] = -np.inf
        second = np.maximum.reduceat(masked, starts)
        best_other = np.where(np.arange(len(s)) == arg[rows], second[rows], first[rows])
        R = damping * R + (1 - damping) * (s - best_other)
        # availability: a(i,k) = min(0, r(k,k) + sum over i' not in {i, k} of max(0, r(i',k)))
        Rp = np.where(is_self, R, np.maximum(R, 0.0))
        column = np.bincount(cols, weights=Rp, minlength=n)
        new_A = column[cols] - Rp
        new_A = np.where(is_self, new_A, np.minimum(new_A, 0.0))
        A = damping * A + (1 - damping) * new_A
        exemplar = (A[self_at] + R[self_at]) > 0
        history[:, it % convergence_iter] = exemplar
        if it >= convergence_iter:
            steady = history.sum(axis=1)
            if np.all((steady == convergence_iter) | (steady == 0)) and exemplar.any():
                break
    exemplars = np.flatnonzero(exemplar)
    if len(exemplars) == 0:
        return exemplars, np.full(n, -1, np.int64)
    exemplars = _refine_exemplars(rows, cols, s, exemplars, n)
    return exemplars, _assign(rows, cols, s, exemplars, n)


def _assign(rows, cols, s, exemplars: np.ndarray, n: int) -> np.ndarray:
    """Each item's most similar exemplar (an exemplar its own), -1 with none adjacent."""
    slot = np.full(n, -1, np.int64)
    slot[exemplars] = np.arange(len(exemplars))
    onto = slot[cols] >= 0
    score = np.where(onto, s, -np.inf)
    score[rows == cols] = np.where(slot[rows[rows == cols]] >= 0, np.inf, -np.inf)
    best = np.full(n, -np.inf)
    np.maximum.at(best, rows, score)
    hit = onto & (score == best[rows]) & (best[rows] > -np.inf)
    assignment = np.full(n, -1, np.int64)
    assignment[rows[hit][::-1]] = slot[cols[hit]][::-1]  # ties: the first exemplar
    return assignment


def _refine_exemplars(rows, cols, s, exemplars: np.ndarray, n: int) -> np.ndarray:
    """scikit-learn's last step: in each cluster, the member whose summed similarity from
    the other members is largest becomes the exemplar. A member lacking a pair to any
    other member cannot stand for the cluster."""
    assignment = _assign(rows, cols, s, exemplars, n)
    same = (assignment[rows] == assignment[cols]) & (assignment[rows] >= 0)
    total = np.bincount(cols[same], weights=s[same], minlength=n)
    reached = np.bincount(cols[same], minlength=n)
    size = np.bincount(assignment[assignment >= 0], minlength=len(exemplars))
    member = assignment >= 0
    full = member & (reached == np.where(member, size[np.maximum(assignment, 0)], -1))
    candidates = np.flatnonzero(full)
    order = np.lexsort((-total[candidates], assignment[candidates]))
    ranked = candidates[order]
    cluster = assignment[ranked]
    first = np.ones(len(ranked), bool)
    first[1:] = cluster[1:] != cluster[:-1]
    out = exemplars.copy()
    out[cluster[first]] = ranked[first]  # the largest total; ties to the lowest index
    return np.unique(out)
