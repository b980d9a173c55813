"""A one-node model of a tension-only spring under semi-implicit Euler: x'' = -w^2 x where
x > 0 (the spring taut), -r w^2 x where x < 0 (only the softer rest of the cloth), w = 1.
For each step w dt (0.5 to 2, the linear bound) an X where the energy grew 100-fold in
100 000 steps from x = 1, v = 0.3. Run: ``python tools/lab/kink_oscillator.py``."""

from __future__ import annotations

import numpy as np


def grows(h: float, r: float, steps: int = 100_000) -> bool:
    x, v, e0 = 1.0, 0.3, None
    for s in range(steps):
        k = 1.0 if x > 0 else r
        v -= h * k * x
        x += h * v
        if s == 100:
            e0 = 0.5 * v * v + 0.5 * (1.0 if x > 0 else r) * x * x
        if abs(x) > 1e6:
            return True
    e = 0.5 * v * v + 0.5 * (1.0 if x > 0 else r) * x * x
    return e > 100 * e0


def main() -> None:
    steps = np.arange(0.5, 2.0, 0.025)
    print("w dt from", steps[0], "by 0.025 to", round(steps[-1], 3))
    for r in (0.0, 0.1, 0.3, 0.5):
        row = "".join("X" if grows(h, r) else "." for h in steps)
        first = next((f"{h:.3f}" for h in steps if grows(h, r)), "none")
        print(f"soft share {r}: {row}  (first {first})")


if __name__ == "__main__":
    main()
