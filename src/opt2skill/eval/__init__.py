"""The paper's evaluation: tracking metrics, statistics over trajectories, comparisons."""
