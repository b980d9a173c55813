"""A room that goes non-finite on its own, for the tests of a room stopped by its engine
(test_faults, test_conformance)."""

from __future__ import annotations

from clothball.game.sim.scene import Scene


def unstable_scene() -> Scene:
    """Past the stability bound on purpose (one substep per frame, two-sided springs just
    too stiff for it): rounding errors grow until the state is non-finite, after 3.7 s of
    frames (CPU float64), long after a test's clients have joined however loaded the
    machine is. Tension-only springs would not do: with the cloth assembled cell by cell
    the wild cloth's springs go slack and its damping wins (k = 2000 N/m, the scene these
    tests had, settles; with uniform masses it blew up after 1.1 s); two-sided ones stay
    stiff, and past k = 2 100 N/m one substep grows them (2 300: after 0.5 s)."""
    s = Scene.load("classic").with_changes(
        {"cloth": {"n": 12, "k_structural": 2200.0, "structural_two_sided": True},
         "sim": {"substeps": 1, "allow_unstable": True}})
    s.name = "unstable"
    return s
