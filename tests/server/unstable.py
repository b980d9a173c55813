"""A room that goes non-finite on its own, for the tests of a room stopped by its engine
(test_faults, test_conformance)."""

from __future__ import annotations

from clothball.game.sim.scene import Scene


def unstable_scene() -> Scene:
    """Past the stability bound on purpose (one substep per frame, two-sided springs just
    too stiff for it): rounding errors grow until the state is non-finite, after 1.8 s of
    frames (CPU float64), after a test's clients have joined however loaded the machine
    is. Tension-only springs would not do: with the cloth assembled cell by cell the wild
    cloth's springs go slack and its damping wins (k = 2000 N/m, the scene these tests had,
    settles; with uniform masses it blew up after 1.1 s); two-sided ones stay stiff. Where
    one substep starts to grow them depends on the grip's shares: past 2 100 N/m with the
    shares sampled at the nodes, past 2 200 with the hat-function shares (2 200 settles for
    15 s; 2 220, 2 240, 2 260, 2 300 go after 4.6, 1.8, 1.0, 1.0 s: chaotic, so not in
    order)."""
    s = Scene.load("classic").with_changes(
        {"cloth": {"n": 12, "k_structural": 2240.0, "structural_two_sided": True},
         "sim": {"substeps": 1, "allow_unstable": True}})
    s.name = "unstable"
    return s
