"""Example tests of a small game (game.py) against a private volfxd, written with volfx.testing.

Copy this folder to start your own suite. It runs with the standard library alone,

    VOLFX_VOLFXD=/path/to/volfxd python3 -m unittest discover -s . -v

and with pytest, which collects unittest test cases as they are (``pytest -q``). One volfxd
serves the class (started on a free port with its own data directory and token, stopped at
the end); each test gets a fresh scene, so no test sees another's state. Golden images live in
golden/; ``VOLFX_UPDATE_GOLDEN=1`` rewrites them after an intended change of the picture.
"""

import os
import sys
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
try:
    import volfx  # noqa: F401
except ImportError:  # Run from volfx's source tree without PYTHONPATH.
    sys.path.insert(0, os.path.join(HERE, "..", ".."))
from volfx import testing  # noqa: E402

sys.path.insert(0, HERE)
import game  # noqa: E402


class GameTests(testing.TestCase):
    def setUp(self):
        super().setUp()
        self.arena = game.Arena(self.scene)

    def test_spell_reaches_the_enemy(self):
        """Game logic: a spell flies 3 units at 2 units/s, so it hits after 1.5 s of game time:
        90 ticks of the scene's 1/60 s, not one tick earlier."""
        self.arena.cast()
        self.arena.tick(89)
        self.assertFalse(self.arena.enemy_hit())
        self.arena.tick(1)
        self.assertTrue(self.arena.enemy_hit())

    def test_arena_looks_right(self):
        """The picture: the arena's objects after a spell was cast, against a golden image.
        The tolerance allows for another CPU or OpenCL device rounding differently."""
        self.arena.cast()
        self.arena.tick(45)
        frame = self.arena.screenshot(64, 48)
        testing.assert_frame_matches(frame, os.path.join(HERE, "golden", "arena_45.png"),
                                     tolerance=3, max_pixels=8)

    def test_replay_gives_the_same_frame(self):
        """Determinism: a game loop of 60 single ticks and one tick of 60 reach the same frame,
        byte for byte, because the scene's clock counts frames, not wall-clock time."""
        self.arena.cast()
        for _ in range(60):
            self.arena.tick()
        looped = self.arena.screenshot(48, 32)
        with testing.Scene(self.client) as other:
            replay = game.Arena(other)
            replay.cast()
            replay.tick(60)
            self.assertEqual(replay.spell_position(), self.arena.spell_position())
            self.assertEqual(replay.screenshot(48, 32), looped)


if __name__ == "__main__":
    unittest.main()
