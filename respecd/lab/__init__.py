"""Offline tooling the daemon never imports: detector training and evaluation, policy
training and the simulated experiment, benchmarks and report figures."""
