"""The trainer every trained component shares, and what it reads and writes.

- :mod:`.trainer`: :class:`~.trainer.Trainer` (optimisation, EMA, validation, checkpoints, resume);
- :mod:`.trainer_state`: what a checkpoint's trainer state holds (optimizer and RNG states, EMA, counters);
- :mod:`.optimizers`: Adam/AdamW over parameter groups with their own learning-rate scale;
- :mod:`.settings`: :class:`~.settings.TrainConfig`, a stage's training options;
- :mod:`.precision`: what ``precision: auto`` means on each device, bf16 autocast;
- :mod:`.checkpoints`: a run's step folders, the newest good one, EMA weights;
- :mod:`.batches`: the data order, a pure function of (seed, epoch);
- :mod:`.processes`: stop signals and the data-parallel context under ``torchrun``.
"""
