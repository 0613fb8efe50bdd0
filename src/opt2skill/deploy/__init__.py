"""Deployment: ONNX export of a trained actor with the metadata a robot needs (`deploy.export`),
and a standalone 2 kHz sim-to-sim player using only that file (`deploy.player`, `deploy.sim_to_sim`;
these import nothing of the training code). docs/deploy.md."""
