"""Counterfactual replay of a recorded session: the replay run, lockstep clock, pacing,
latency model and report."""
