"""Whole-body trajectory optimization (Crocoddyl): tasks, problem builders, solvers."""
