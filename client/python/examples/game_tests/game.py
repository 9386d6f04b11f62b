"""A very small "game" drawn by volfxd, for the example tests beside it: an arena with a floor,
the player (a box) and an enemy (a sphere); the player casts spells, energy waves that fly from
the player toward the enemy at a fixed speed. The game keeps no clock of its own: one game tick
is one ``sim.step`` of volfxd's scene, so the game is as deterministic as the scene is.
"""

PLAYER = [-1.5, 0.5, 0.0]
ENEMY = [1.5, 0.5, 0.0]
SPELL_SPEED = 2.0  # world units per second of scene time
HIT_DISTANCE = 1e-6


class Arena:
    """The game on one volfxd scene (a ``volfx.testing.Scene`` or anything with the same
    ``patch``, ``get``, ``step`` and ``render``)."""

    def __init__(self, scene):
        self.scene = scene
        scene.patch({
            "objects": [
                {"id": "floor", "shape": "plane", "position": [0, 0, 0],
                 "color": [0.5, 0.5, 0.45]},
                {"id": "player", "shape": "box", "position": PLAYER, "scale": [0.6, 1, 0.6],
                 "color": [0.2, 0.4, 0.9]},
                {"id": "enemy", "shape": "sphere", "position": ENEMY, "color": [0.9, 0.25, 0.2]},
            ],
            "waves": [],
            "camera": {"eye": [0, 3, 6], "target": [0, 0.5, 0]},
        })
        self.spells = 0

    def cast(self):
        """The player casts a spell: a wave at the player, flying toward the enemy."""
        wave = {"id": "spell%d" % self.spells, "center": PLAYER, "direction": [1, 0, 0],
                "length": 0.5, "radius": 0.6,
                "animate": [{"field": "center", "target": ENEMY, "rate": SPELL_SPEED}]}
        self.scene.set("waves.%d" % self.spells, wave)
        self.spells += 1

    def tick(self, n=1):
        """Advances the game by 'n' ticks (scene frames)."""
        return self.scene.step(n)

    def spell_position(self, i=0):
        return self.scene.get("waves.%d.center" % i)

    def enemy_hit(self):
        """True once any spell has reached the enemy."""
        for i in range(self.spells):
            pos = self.spell_position(i)
            if sum((p - e) ** 2 for p, e in zip(pos, ENEMY)) <= HIT_DISTANCE ** 2:
                return True
        return False

    def screenshot(self, width=64, height=48, layers=None):
        kw = {"layers": layers} if layers else {}
        return self.scene.render(width, height, **kw)
