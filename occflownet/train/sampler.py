"""Deterministic, resumable, sharded batch order: the samples of step ``s`` are a pure function of (seed, s).

Every epoch is a permutation drawn from ``default_rng(seed + epoch)``; global step ``s`` takes the slice
``[k*G, (k+1)*G)`` of epoch ``s // steps_per_epoch`` with ``G = batch_size * world_size`` and rank ``r`` its
``batch_size`` items. A resumed run therefore sees exactly the data an uninterrupted run would, with no sampler
state to save, and ranks never overlap within a step.
"""
from __future__ import annotations

import numpy as np
from torch.utils.data import Sampler


class StepBatchSampler(Sampler):
    """Yields, for steps ``start_step .. max_steps-1``, a list of ``(sample_index, step)`` keys for this rank."""

    def __init__(self, num_samples: int, batch_size: int, seed: int, start_step: int, max_steps: int,
                 rank: int = 0, world_size: int = 1):
        if num_samples < 1:
            raise ValueError("the training split has no samples")
        self.num_samples = num_samples
        self.batch_size = batch_size
        self.seed = seed
        self.start_step = start_step
        self.max_steps = max_steps
        self.rank = rank
        self.world_size = world_size
        global_batch = batch_size * world_size
        # Small datasets: an "epoch" may repeat samples so that every step has a full global batch.
        self.repeats = int(np.ceil(global_batch / num_samples))
        self.steps_per_epoch = max(1, (num_samples * self.repeats) // global_batch)

    def keys_for_step(self, step: int) -> list[tuple[int, int]]:
        epoch, k = divmod(step, self.steps_per_epoch)
        order = np.random.default_rng(self.seed + epoch).permutation(np.tile(np.arange(self.num_samples), self.repeats))
        g = self.batch_size * self.world_size
        chunk = order[k * g:(k + 1) * g]
        mine = chunk[self.rank * self.batch_size:(self.rank + 1) * self.batch_size]
        return [(int(i), step) for i in mine]

    def __iter__(self):
        for step in range(self.start_step, self.max_steps):
            yield self.keys_for_step(step)

    def __len__(self) -> int:
        return max(0, self.max_steps - self.start_step)
