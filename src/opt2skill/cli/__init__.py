"""The `opt2skill` command. Each area registers its commands from its own module."""

import os

# Torch's OpenMP threads (libgomp) spin up to 300,000 times waiting for each other before they sleep.
# With another process on one of the cores, that spinning made a training 4.3 times slower on 2 cores
# (its PPO update 7 times); 10,000 spins cost nothing measurable alone and halve the loss
# (benchmarks/shared_cores.py, docs/training.md "Sharing the cores"). libgomp reads it once, when torch
# loads, which no command has done yet here; a user's own GOMP_SPINCOUNT or OMP_WAIT_POLICY wins.
SPINCOUNT = "10000"
if "GOMP_SPINCOUNT" not in os.environ and "OMP_WAIT_POLICY" not in os.environ:
    os.environ["GOMP_SPINCOUNT"] = SPINCOUNT
