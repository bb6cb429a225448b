"""Simulated captures with known truth: the paper's protocol (`simulate`), phones on their own clocks (`phones`), a
point in flight (`flight`), and scoring against the truth (`evaluate`). Imports `reconstruct`; nothing imports it
except the CLI, the demo, the tests and the benchmarks."""
