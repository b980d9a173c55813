"""The physics lab: accuracy against cost, reference integrators, energy, benchmarks."""
