"""RJMCMC with simulated annealing (the DEM-blocks paper, section 3.3): the block of one
support changes at each iteration, by one of three kernels.

- Q1, uniform jumps: a form, a variant and parameters drawn uniformly;
- Q2, data-driven jumps: a form drawn uniformly, its gutter and top heights from
  N(H_g, 1 m) and N(H_t, 1 m), H_g and H_t estimated from the support's DSM; half of
  them switch the form keeping the parameters it shares with the current block (a
  gambrel becomes a mansard of the same heights and inset), the dimension-matching
  jump between nested forms;
- Q3, regularisation jumps: a form drawn uniformly among the neighbours' (and the
  block's own), its parameters from a Gaussian mixture centred on theirs.

The density is h^(1 / T_t) with a geometric decrease of T_t from White's initial
temperature (the spread of the energy's changes at infinite temperature). The
exploration stage draws Q2 mostly (q = 0.1, 0.8, 0.1); once fewer than 5 % of the
uniform and data-driven proposals of 1,000 iterations are accepted (the paper's
footnote 4 counts every kernel's; the regularisation kernel's small steps are accepted
long after the exploration is over) the adjustment stage draws Q3 mostly (0.1, 0.1,
0.8). The kernels are taken as symmetric: the acceptance ratio is the
density's alone (a departure, ``docs/blocks.md``), which under annealing changes the
path the chain takes, not the optimum it is driven to.

At zero temperature the best configuration met is made a local minimum over the forms
(:func:`form_sweep`) and then over the parameters (:func:`polish`), deterministically.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from .energy import likelihood, max_distance, pair_energy
from .library import (
    FORMS,
    RIDGED,
    Block,
    Frame,
    block_heights,
    orientation_free,
    parameter_ranges,
    ridge_frame,
    valid_params,
)

KERNELS = ("uniform", "data-driven", "regularisation")
_EXPLORE = (0.1, 0.8, 0.1)  # the paper's q_i in the exploration stage
_ADJUST = (0.1, 0.1, 0.8)  # and once the acceptance rate falls below _STAGE_RATE
_STAGE_RATE = 0.05
_WINDOW = 1000  # iterations over which the acceptance rate is computed
_DATA_SIGMA = 1.0  # metres: the data-driven kernel's spread (the paper's sigma)
_SWITCH = 0.5  # data-driven jumps that keep the parameters the new form shares
_MIXTURE_SIGMAS = (0.5, 0.1, 0.02)  # metres: the regularisation kernel's components
_COOLING_SPAN = 1e-4  # the final temperature as a share of the initial one
_WHITE_PROBES = 200  # proposals from the initial state that estimate T_0
_TRACE_EVERY = 50
_POLISH_EVALUATIONS = 300  # Powell's evaluations per block at the end
_SWEEP_EVALUATIONS = 100  # and per start of each form the sweep tries


@dataclass
class SupportData:
    """One support and the DSM on it.

    frame : the support's frame; ends : (4,) bool, its sides u0, v0, u1, v1 that are
    junctions; u, v, z : (n,) its cells in the frame and their DSM heights, metres;
    strips : {side: (j, idx, u, v)} for each junction side, the neighbour j it leads to
    and the cells of j (indices into j's, and their u, v in this frame) over which a
    ridge running into that side carries the roof on."""

    frame: Frame
    ends: tuple[bool, bool, bool, bool]
    u: np.ndarray
    v: np.ndarray
    z: np.ndarray
    strips: dict = field(default_factory=dict)

    def __post_init__(self):
        z = self.z
        self.z_lo = float(np.percentile(z, 1)) - 1.0
        self.z_hi = float(np.percentile(z, 99)) + 1.0
        self.gutter_hat = float(np.percentile(z, 10))  # H_g: the eaves are the lowest roof
        self.top_hat = float(np.percentile(z, 95))  # H_t: the ridge the highest

    def ranges(self, form: str, along: int) -> np.ndarray:
        L, W, _ = ridge_frame(self.frame, along, self.ends)
        return parameter_ranges(form, L, W, self.z_lo, self.z_hi)

    def heights(self, block: Block) -> np.ndarray:
        return block_heights(block, self.u, self.v, self.frame, self.ends)


@dataclass
class Pair:
    """Two neighbouring supports i < j and the unit vector of their common edge."""

    i: int
    j: int
    edge: np.ndarray


@dataclass
class Annealing:
    """What the sampler returns: the best configuration met, its energy, the trace
    (iteration, temperature, energy every ``_TRACE_EVERY`` iterations), the proposals
    and acceptances per kernel, when the adjustment stage began (None: never, the
    schedule did not converge in the iterations given), and at zero temperature the
    energy's evaluations (:func:`form_sweep`, :func:`polish`), the blocks whose form the
    sweep changed and the seconds they took."""

    blocks: list[Block]
    energy: float
    likelihoods: list[float]
    prior: float
    iterations: int
    trace: list = field(default_factory=list)
    proposed: dict = field(default_factory=dict)
    accepted: dict = field(default_factory=dict)
    adjustment_from: int | None = None
    t_start: float = 0.0
    t_end: float = 0.0
    zero_temperature_evaluations: int = 0
    forms_switched: int = 0
    zero_temperature_seconds: float = 0.0


def initial_blocks(supports: list[SupportData]) -> list[Block]:
    """x_0: every support a flat block at its DSM's median."""
    return [Block("flat", 0, False, (float(np.median(s.z)),)) for s in supports]


class _Chain:
    """The configuration and its energy terms, updated one support at a time.

    A block whose ridge runs into a junction carries its roof on over the neighbour's
    half next to it (:attr:`SupportData.strips`), as an L's arm runs on into the other
    arm's roof up to the valleys: the neighbour's cells see the higher of the two roofs,
    so changing a block changes its neighbours' likelihoods too."""

    def __init__(self, supports, pairs, blocks, alpha, beta, form_cost=0.0):
        self.supports, self.pairs, self.alpha, self.beta = supports, pairs, alpha, beta
        self.form_cost = form_cost
        self.blocks = list(blocks)
        self.of = [[] for _ in supports]
        for k, p in enumerate(pairs):
            self.of[p.i].append(k)
            self.of[p.j].append(k)
        self.into = [sorted({i for i, s in enumerate(supports) for j, *_ in s.strips.values()
                             if j == t}) for t in range(len(supports))]  # fmt: skip
        self.base = [s.heights(b) for s, b in zip(supports, self.blocks, strict=True)]
        self.ext = {}
        for i, b in enumerate(self.blocks):
            self.ext.update(self.extensions(i, b))
        self.lik = [self.likelihood(j, self.base[j], self.blocks[j], self.ext)
                    for j in range(len(supports))]  # fmt: skip
        self.pair = [self.pair_term(p, self.blocks[p.i], self.blocks[p.j]) for p in pairs]

    def extensions(self, i: int, block: Block) -> dict:
        """{(i, j): (n_j,) the block's roof carried on over support j's cells (-inf off
        it)} for every neighbour j a junction of support i leads to."""
        s = self.supports[i]
        out = {}
        for side, (j, idx, u, v) in s.strips.items():
            arr = out.setdefault((i, j), np.full(len(self.supports[j].z), -np.inf))
            if block.form in RIDGED and side % 2 == block.along:  # the ridge runs into it
                arr[idx] = block_heights(block, u, v, s.frame, s.ends)
        return out

    def likelihood(self, j: int, base: np.ndarray, block: Block, ext: dict) -> float:
        """Gamma_j of the higher of support j's roof and those carried over it, raised by
        ``form_cost`` (a share) per parameter of its form beyond one."""
        model = base
        for i in self.into[j]:
            if (i, j) in ext:
                model = np.maximum(model, ext[(i, j)])
        occam = 1.0 + self.form_cost * (len(block.params) - 1)
        return likelihood(model, self.supports[j].z, self.alpha) * occam

    def ridge(self, i: int, block: Block) -> np.ndarray:
        return self.supports[i].frame.axis(block.along)

    def pair_term(self, p: Pair, a: Block, b: Block) -> float:
        if a.form != b.form:
            return 0.0
        d_max = max_distance(self.supports[p.i].ranges(a.form, a.along),
                             self.supports[p.j].ranges(b.form, b.along))  # fmt: skip
        return pair_energy(a, b, self.ridge(p.i, a), self.ridge(p.j, b), p.edge, d_max,
                           self.beta)  # fmt: skip

    @property
    def energy(self) -> float:
        return float(sum(self.lik) + sum(self.pair))

    def change(self, i: int, block: Block) -> tuple[float, tuple, dict]:
        """Delta U of giving support i ``block``, with the new terms."""
        base = self.supports[i].heights(block)
        new_ext = self.extensions(i, block)
        ext = {**self.ext, **new_ext} if new_ext else self.ext
        liks = {i: self.likelihood(i, base, block, ext)}
        for _, j in new_ext:
            liks[j] = self.likelihood(j, self.base[j], self.blocks[j], ext)
        new_pairs = {}
        for k in self.of[i]:
            p = self.pairs[k]
            a = block if p.i == i else self.blocks[p.i]
            b = block if p.j == i else self.blocks[p.j]
            new_pairs[k] = self.pair_term(p, a, b)
        delta = sum(v - self.lik[k] for k, v in liks.items())
        delta += sum(new_pairs[k] - self.pair[k] for k in new_pairs)
        return delta, (base, new_ext, liks), new_pairs

    def accept(self, i: int, block: Block, state: tuple, new_pairs: dict) -> None:
        base, new_ext, liks = state
        self.blocks[i], self.base[i] = block, base
        self.ext.update(new_ext)
        for k, v in liks.items():
            self.lik[k] = v
        for k, e in new_pairs.items():
            self.pair[k] = e


def _uniform(rng, s: SupportData, _chain, _i) -> Block:
    form = str(rng.choice(list(FORMS)))
    along = 0 if orientation_free(form) else int(rng.integers(2))
    r = s.ranges(form, along)
    params = valid_params(form, rng.uniform(r[:, 0], r[:, 1]), r)
    return Block(form, along, bool(rng.random() < 0.5), tuple(params))


def _data_driven(rng, s: SupportData, chain: _Chain, i: int) -> Block:
    form = str(rng.choice(list(FORMS)))
    along = 0 if orientation_free(form) else int(rng.integers(2))
    r = s.ranges(form, along)
    p = rng.uniform(r[:, 0], r[:, 1])
    names = FORMS[form][1]
    p[0] = rng.normal(s.gutter_hat, _DATA_SIGMA)
    if "h_top" in names:
        p[names.index("h_top")] = rng.normal(s.top_hat, _DATA_SIGMA)
        for mid in ("h_hip", "h_break"):  # between the two estimates
            if mid in names:
                lo, hi = sorted((p[0], p[names.index("h_top")]))
                p[names.index(mid)] = rng.uniform(lo, hi)
    elif form == "flat":
        p[0] = rng.normal(float(np.median(s.z)), _DATA_SIGMA)
    own = chain.blocks[i]
    if form != own.form and rng.random() < _SWITCH:  # a switch: the shared parameters kept
        along = own.along if not orientation_free(form) else 0
        r = s.ranges(form, along)
        had = dict(zip(FORMS[own.form][1], own.params, strict=True))
        p = np.array([had.get(n, v) for n, v in zip(names, p, strict=True)])
    return Block(form, along, bool(rng.random() < 0.5), tuple(valid_params(form, p, r)))


def _regularisation(rng, s: SupportData, chain: _Chain, i: int) -> Block:
    own = chain.blocks[i]
    sources = [own] + [chain.blocks[p.j if p.i == i else p.i] for p in
                       (chain.pairs[k] for k in chain.of[i])]  # fmt: skip
    k = int(rng.integers(len(sources)))
    src = sources[k]
    if k == 0:
        along = own.along
    else:  # the ridge aligned with the neighbour's
        j = chain.pairs[chain.of[i][k - 1]]
        ridge = chain.ridge(j.j if j.i == i else j.i, src)
        along = int(abs(s.frame.axis(1) @ ridge) > abs(s.frame.axis(0) @ ridge))
    if orientation_free(src.form):
        along = 0
    r = s.ranges(src.form, along)
    sigma = _MIXTURE_SIGMAS[int(rng.integers(len(_MIXTURE_SIGMAS)))]
    step = rng.normal(0.0, sigma, len(src.params))
    if k == 0 and rng.random() < 0.5:  # the block's own: one parameter at a time, half the
        step[np.arange(len(step)) != rng.integers(len(step))] = 0.0  # time (coupled ones)
    p = np.asarray(src.params) + step
    return Block(src.form, along, src.flip, tuple(valid_params(src.form, p, r)))


_PROPOSE = (_uniform, _data_driven, _regularisation)


def _descend(chain: _Chain, i: int, block: Block, evaluations: int) -> tuple[float, Block, int]:
    """Powell's method from ``block`` on support i's parameters, its form and variant
    and its neighbours fixed: the energy change at the minimum, the block there and the
    evaluations."""
    s = chain.supports[i]
    r = s.ranges(block.form, block.along)

    def energy(p):
        params = tuple(valid_params(block.form, np.asarray(p), r))
        return chain.change(i, Block(block.form, block.along, block.flip, params))[0]

    res = optimize.minimize(energy, np.asarray(block.params), method="Powell", options={
        "xtol": 1e-3, "ftol": 1e-6, "maxfev": evaluations})  # fmt: skip
    params = tuple(valid_params(block.form, res.x, r))
    return float(res.fun), Block(block.form, block.along, block.flip, params), res.nfev


def polish(chain: _Chain) -> int:
    """The annealing's end at zero temperature: each block's parameters descended to the
    nearest minimum of the energy (Powell's method, its form and variant kept, its
    neighbours fixed). Random steps crawl along the narrow valleys where parameters
    trade against each other (a mansard's gutter, break and inset); the paper names
    jump-diffusion as its future work for the same reason. Returns the evaluations."""
    evaluations = 0
    for i in range(len(chain.supports)):
        delta, new, n = _descend(chain, i, chain.blocks[i], _POLISH_EVALUATIONS)
        evaluations += n
        if delta < 0:
            chain.accept(i, new, *chain.change(i, new)[1:])
    return evaluations


def form_starts(s: SupportData, form: str, along: int, flip: bool, own: Block) -> list[Block]:
    """Where a zero-temperature jump to ``form`` starts: the data-driven kernel's
    estimates (gutter at H_g, top at H_t, a break or hip height between them, the rest
    mid-range), and the same with the parameters it shares with the block ``own`` the
    support has (the switch jump's)."""
    names = FORMS[form][1]
    r = s.ranges(form, along)
    p = r.mean(axis=1)
    if form == "flat":
        p[0] = float(np.median(s.z))
    else:
        p[0] = s.gutter_hat
        if "h_top" in names:
            p[names.index("h_top")] = s.top_hat
        for mid in ("h_hip", "h_break"):
            if mid in names:
                p[names.index(mid)] = s.gutter_hat + 0.6 * (s.top_hat - s.gutter_hat)
    had = dict(zip(FORMS[own.form][1], own.params, strict=True))
    shared = np.array([had.get(n, v) for n, v in zip(names, p, strict=True)])
    starts = [p] if np.allclose(shared, p) else [p, shared]
    return [Block(form, along, flip, tuple(valid_params(form, q, r))) for q in starts]


def best_of_form(chain: _Chain, i: int, form: str) -> tuple[float, Block | None, int]:
    """Support i's best block of ``form`` (every variant, from :func:`form_starts`, by
    :func:`_descend`) with its neighbours fixed: the energy change, the block and the
    evaluations."""
    best, block, evaluations = np.inf, None, 0
    for along in (0,) if orientation_free(form) else (0, 1):
        for flip in (False, True) if form == "shed" else (False,):
            for start in form_starts(chain.supports[i], form, along, flip, chain.blocks[i]):
                delta, new, n = _descend(chain, i, start, _SWEEP_EVALUATIONS)
                evaluations += n
                if delta < best:
                    best, block = delta, new
    return best, block, evaluations


def form_sweep(chain: _Chain) -> tuple[_Chain, int, int]:
    """The annealing's end at zero temperature over the forms too: the configuration
    made a local minimum for a change of form, as :func:`polish` makes it one for the
    parameters.

    The annealing ends in the form it last crossed into while it was warm: four hipped
    roofs of seeds 0-2 ended as mansards 5-31 % higher in energy than the hipped roof
    it did not try once cold. So, deterministically:

    1. for a building of several supports, each form given to all of them at once (from
       the data-driven estimates, the ridge along each support's longer side), then each
       support's best block of that form (:func:`best_of_form`) taken in turn; kept if
       the building's energy falls. One
       support at a time could not leave a form: it would lose its neighbours' joinable
       prior;
    2. each support's block replaced by the best of every form (both ridge axes, from
       :func:`form_starts`) where the energy falls, its neighbours fixed.

    Returns the chain (a new one where step 1 changed the forms), the evaluations of the
    energy and how many blocks changed form."""
    evaluations = 0
    forms_before = [b.form for b in chain.blocks]
    if len(chain.supports) > 1:
        for form in FORMS:
            start = []
            for s, b in zip(chain.supports, chain.blocks, strict=True):
                u0, u1, v0, v1 = s.frame.rect
                along = 0 if orientation_free(form) else int(v1 - v0 > u1 - u0)
                start.append(form_starts(s, form, along, False, b)[0])
            trial = _Chain(chain.supports, chain.pairs, start, chain.alpha, chain.beta,
                           chain.form_cost)  # fmt: skip
            for i in range(len(trial.supports)):
                delta, new, n = best_of_form(trial, i, form)
                evaluations += n
                if delta < 0:
                    trial.accept(i, new, *trial.change(i, new)[1:])
            if trial.energy < chain.energy:
                chain = trial
    for i in range(len(chain.supports)):
        for form in FORMS:
            delta, new, n = best_of_form(chain, i, form)
            evaluations += n
            if delta < 0:
                chain.accept(i, new, *chain.change(i, new)[1:])
    changed = sum(a != b.form for a, b in zip(forms_before, chain.blocks, strict=True))
    return chain, evaluations, changed


def anneal(
    supports: list[SupportData],
    pairs: list[Pair],
    *,
    alpha: float,
    beta: float,
    iterations: int,
    seed,
    form_cost: float = 0.0,
) -> Annealing:
    """Simulated annealing of the blocks of one building's supports.

    Parameters
    ----------
    supports : list of SupportData
    pairs : list of Pair
        The neighbouring supports (a common edge).
    alpha : float
        Eq. 3's exponent.
    beta : float
        Eq. 4's weight of the prior.
    iterations : int
        The most iterations (the schedule cools from T_0 to T_0 * 1e-4 over them).
    seed : int or sequence of int
    form_cost : float
        Share by which each parameter of a form beyond the first raises its support's
        likelihood energy (0: the paper's energy).

    Returns
    -------
    Annealing
    """
    rng = np.random.default_rng(seed)
    chain = _Chain(supports, pairs, initial_blocks(supports), alpha, beta, form_cost)
    n = len(supports)
    probes = []
    for _ in range(_WHITE_PROBES):  # White: T_0 from the energy's spread at T = infinity
        i = int(rng.integers(n))
        kernel = _PROPOSE[int(rng.integers(2))]
        probes.append(chain.change(i, kernel(rng, supports[i], chain, i))[0])
    t0 = max(float(np.std(probes)), 1e-6)
    cooling = _COOLING_SPAN ** (1.0 / max(iterations, 1))
    temperature = t0
    best_blocks, best_energy = list(chain.blocks), chain.energy
    proposed = dict.fromkeys(KERNELS, 0)
    accepted = dict.fromkeys(KERNELS, 0)
    q = _EXPLORE
    adjustment_from = None
    window = 0
    trace = [(0, round(t0, 6), round(chain.energy, 4))]
    for it in range(1, iterations + 1):
        k = int(rng.choice(3, p=q))
        i = int(rng.integers(n))
        block = _PROPOSE[k](rng, supports[i], chain, i)
        delta, lik, new_pairs = chain.change(i, block)
        proposed[KERNELS[k]] += 1
        if delta <= 0 or rng.random() < np.exp(-delta / temperature):
            chain.accept(i, block, lik, new_pairs)
            accepted[KERNELS[k]] += 1
            window += k < 2  # the exploration kernels' acceptances mark the stage
            e = chain.energy
            if e < best_energy:
                best_blocks, best_energy = list(chain.blocks), e
        if it % _WINDOW == 0:
            if adjustment_from is None and window < _STAGE_RATE * _WINDOW * sum(q[:2]):
                adjustment_from, q = it, _ADJUST
            window = 0
        if it % _TRACE_EVERY == 0:
            trace.append((it, round(temperature, 6), round(chain.energy, 4)))
        temperature *= cooling
    t_cold = time.perf_counter()
    final = _Chain(supports, pairs, best_blocks, alpha, beta, form_cost)
    final, evaluations, switched = form_sweep(final)
    evaluations += polish(final)
    cold_s = time.perf_counter() - t_cold
    trace.append((iterations + evaluations, 0.0, round(final.energy, 4)))
    return Annealing(final.blocks, final.energy, final.lik, float(sum(final.pair)), iterations,
                     trace, proposed, accepted, adjustment_from, t0, temperature,
                     evaluations, switched, cold_s)  # fmt: skip
