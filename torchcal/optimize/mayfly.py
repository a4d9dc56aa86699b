"""The Mayfly Algorithm (Zervoudakis & Tsafarakis, 2020) with the improvements of the
compensation patent: improved tent-chaos + opposition-based initialization, Cauchy mutation.

Per iteration, with ``g`` the inertia (damped), ``r`` distances in the search space:

* males: ``v = g v + a1 exp(-beta rp^2) (pbest - x) + a2 exp(-beta rg^2) (gbest - x)``; the
  best male does the nuptial dance ``v = g v + dc u``, ``u ~ U(-1, 1)``, ``dc`` damped;
* females, paired with the male of the same rank: attracted ``v = g v + a2 exp(-beta rmf^2)
  (x_m - x_f)`` when the male is better, otherwise random flight ``v = g v + fl u``, ``fl`` damped;
* velocities are clamped to ``vmax_fraction`` of the box, positions to the box;
* mating: ranked pairs produce two offspring by arithmetic crossover; offspring are mutated
  (Cauchy, scale ``mutation_scale`` of the box width, or Gaussian in the plain algorithm);
* replacement: males and females each keep the best of parents plus half of the offspring.

Initialization: the improved tent map ``z <- 2z (z < 0.5), 2(1 - z) (z >= 0.5)`` plus a small
random term ``rand / n`` that keeps the sequence off the map's short cycles, mapped to the box;
opposition-based learning adds ``lower + upper - x`` of every point, and the best half of the
union is kept. Every improvement can be switched off for ablation.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcal.optimize.base import Fitness, Metaheuristic, OptimizeResult, progress_bar


class Mayfly(Metaheuristic):
    """Improved Mayfly optimizer (MMA).

    Args:
        population: males and females each.
        iterations: generations.
        a1, a2, beta: attraction coefficients and visibility.
        gravity, gravity_damping: inertia weight and its per-iteration factor.
        dance, dance_damping: nuptial dance amplitude (fraction of box width) and damping.
        flight, flight_damping: female random flight amplitude and damping.
        vmax_fraction: velocity limit as a fraction of the box width.
        tent_init, opposition_init, cauchy_mutation: the improvements (ablation switches).
        mutation_scale: mutation scale as a fraction of the box width.
    """

    name = "mayfly"

    def __init__(
        self,
        population: int = 20,
        iterations: int = 50,
        a1: float = 1.0,
        a2: float = 1.5,
        beta: float = 2.0,
        gravity: float = 0.8,
        gravity_damping: float = 0.99,
        dance: float = 0.05,
        dance_damping: float = 0.8,
        flight: float = 0.05,
        flight_damping: float = 0.99,
        vmax_fraction: float = 0.1,
        tent_init: bool = True,
        opposition_init: bool = True,
        cauchy_mutation: bool = True,
        mutation_scale: float = 0.02,
    ) -> None:
        self.population, self.iterations = population, iterations
        self.a1, self.a2, self.beta = a1, a2, beta
        self.gravity, self.gravity_damping = gravity, gravity_damping
        self.dance, self.dance_damping = dance, dance_damping
        self.flight, self.flight_damping = flight, flight_damping
        self.vmax_fraction = vmax_fraction
        self.tent_init, self.opposition_init, self.cauchy_mutation = tent_init, opposition_init, cauchy_mutation
        self.mutation_scale = mutation_scale

    # ------------------------------------------------------------------ initialization

    def _unit_samples(self, n: int, dim: int, gen: torch.Generator, dtype) -> torch.Tensor:
        if not self.tent_init:
            return torch.rand(n, dim, generator=gen, dtype=dtype)
        z = torch.rand(dim, generator=gen, dtype=dtype)
        rows = []
        for _ in range(n):
            z = torch.where(z < 0.5, 2.0 * z, 2.0 * (1.0 - z)) + torch.rand(dim, generator=gen, dtype=dtype) / n
            z = torch.remainder(z, 1.0)
            rows.append(z.clone())
        return torch.stack(rows)

    def _initial(self, fitness, lower, upper, gen):
        n, dim = 2 * self.population, lower.shape[0]
        x = lower + self._unit_samples(n, dim, gen, lower.dtype) * (upper - lower)
        if self.opposition_init:
            x = torch.cat([x, lower + upper - x])
        f = fitness(x)
        order = torch.argsort(f)[:n]
        return x[order], f[order], x.shape[0]

    # ------------------------------------------------------------------------- search

    def minimize(self, fitness: Fitness, lower, upper, *, seed: int = 0, progress: bool = False,
                 on_iteration: Callable[[int, float], None] | None = None) -> OptimizeResult:
        """Minimize ``fitness`` over ``[lower, upper]``.

        ``on_iteration(k, best_f)`` is called after iteration ``k`` (1-based) with the best
        fitness so far; it may raise to stop the search (a study pruning a poor trial does).
        """
        gen = torch.Generator().manual_seed(seed)
        width = upper - lower
        vmax = self.vmax_fraction * width
        pop, evaluations = self.population, 0
        x, f, used = self._initial(fitness, lower, upper, gen)
        evaluations += used
        perm = torch.randperm(2 * pop, generator=gen)
        male, female = x[perm[:pop]], x[perm[pop:]]
        f_male, f_female = f[perm[:pop]], f[perm[pop:]]
        v_male, v_female = torch.zeros_like(male), torch.zeros_like(female)
        pbest, f_pbest = male.clone(), f_male.clone()
        k = int(torch.argmin(f))
        gbest, f_gbest = x[k].clone(), float(f[k])
        g, dance, flight = self.gravity, self.dance, self.flight
        history = [f_gbest]
        dtype = lower.dtype
        with progress_bar(progress, self.iterations, "Mayfly search") as bar:
            for _ in range(self.iterations):
                # males
                rp2 = ((pbest - male) ** 2).sum(-1, keepdim=True)
                rg2 = ((gbest - male) ** 2).sum(-1, keepdim=True) / (width**2).sum()
                rp2 = rp2 / (width**2).sum()
                attract = (
                    g * v_male
                    + self.a1 * torch.exp(-self.beta * rp2) * torch.rand(male.shape, generator=gen, dtype=dtype) * (pbest - male)
                    + self.a2 * torch.exp(-self.beta * rg2) * torch.rand(male.shape, generator=gen, dtype=dtype) * (gbest - male)
                )
                dancing = g * v_male + dance * width * (2 * torch.rand(male.shape, generator=gen, dtype=dtype) - 1)
                is_best = (f_male <= f_gbest).unsqueeze(-1)
                v_male = torch.where(is_best, dancing, attract).clamp(-vmax, vmax)
                male = torch.minimum(torch.maximum(male + v_male, lower), upper)
                # females, paired by rank with males
                om, of = torch.argsort(f_male), torch.argsort(f_female)
                male, v_male, f_male = male[om], v_male[om], f_male[om]
                pbest, f_pbest = pbest[om], f_pbest[om]
                female, v_female, f_female = female[of], v_female[of], f_female[of]
                rmf2 = ((male - female) ** 2).sum(-1, keepdim=True) / (width**2).sum()
                toward = g * v_female + self.a2 * torch.exp(-self.beta * rmf2) * torch.rand(female.shape, generator=gen, dtype=dtype) * (male - female)
                wander = g * v_female + flight * width * (2 * torch.rand(female.shape, generator=gen, dtype=dtype) - 1)
                v_female = torch.where((f_female > f_male).unsqueeze(-1), toward, wander).clamp(-vmax, vmax)
                female = torch.minimum(torch.maximum(female + v_female, lower), upper)
                f_male, f_female = fitness(male), fitness(female)
                evaluations += 2 * pop
                better = f_male < f_pbest
                pbest = torch.where(better.unsqueeze(-1), male, pbest)
                f_pbest = torch.where(better, f_male, f_pbest)
                # mating
                om, of = torch.argsort(f_male), torch.argsort(f_female)
                mm, ff = male[om], female[of]
                mix = torch.rand(pop, 1, generator=gen, dtype=dtype)
                offspring = torch.cat([mix * mm + (1 - mix) * ff, mix * ff + (1 - mix) * mm])
                if self.cauchy_mutation:
                    noise = torch.tan(torch.pi * (torch.rand(offspring.shape, generator=gen, dtype=dtype) - 0.5))
                else:
                    noise = torch.randn(offspring.shape, generator=gen, dtype=dtype)
                offspring = offspring + self.mutation_scale * width * noise
                offspring = torch.minimum(torch.maximum(offspring, lower), upper)
                f_off = fitness(offspring)
                evaluations += offspring.shape[0]
                # replacement: parents plus half the offspring each
                cand_m = torch.cat([male, offspring[:pop]])
                cand_fm = torch.cat([f_male, f_off[:pop]])
                cand_vm = torch.cat([v_male, torch.zeros_like(offspring[:pop])])
                keep = torch.argsort(cand_fm)[:pop]
                male, f_male, v_male = cand_m[keep], cand_fm[keep], cand_vm[keep]
                pbest = torch.where((f_male < f_pbest[:pop]).unsqueeze(-1), male, pbest)
                f_pbest = torch.minimum(f_male, f_pbest)
                cand_f = torch.cat([female, offspring[pop:]])
                cand_ff = torch.cat([f_female, f_off[pop:]])
                cand_vf = torch.cat([v_female, torch.zeros_like(offspring[pop:])])
                keep = torch.argsort(cand_ff)[:pop]
                female, f_female, v_female = cand_f[keep], cand_ff[keep], cand_vf[keep]
                for xs, fs in ((male, f_male), (female, f_female)):
                    k = int(torch.argmin(fs))
                    if float(fs[k]) < f_gbest:
                        f_gbest, gbest = float(fs[k]), xs[k].clone()
                g *= self.gravity_damping
                dance *= self.dance_damping
                flight *= self.flight_damping
                history.append(f_gbest)
                bar.advance()
                if on_iteration is not None:
                    on_iteration(len(history) - 1, f_gbest)
        return OptimizeResult(best_x=gbest, best_f=f_gbest, history=history, n_evaluations=evaluations)

    def evaluations_per_run(self) -> int:
        """Fitness calls of one run (for equal-budget comparisons)."""
        init = 4 * self.population if self.opposition_init else 2 * self.population
        return init + self.iterations * 4 * self.population
