"""The version of what the scene generators produce: part of every data cache key and of every
run key (:func:`mrcert.infra.identity.identify`), so that neither a cached image nor a finished
run of an older generator is ever taken for one of this code's."""

GENERATOR_VERSION = 5
"""Bump when scene generation, pose sampling or rendering changes what a config produces
(``tests/test_data.py`` fingerprints the scenes' images so that a change cannot slip by).
2: MetaRoom training poses kept apart from the test poses in every angle (``separation_rule``).
3: MetaRoom objects at twice their modelled size; training poses also kept apart from the
validation poses (tabletop).
4: the MetaRoom's walls, floor, ceiling, door and table of one matte material (Roughcast, as
in the paper's room); the room lit with 0.8 ambient (``metaroom.AMBIENT``, was 0.6); wall
surfaces lit as facing into the room.
5: a patchwork rug (4 m x 4 m, ``metaroom.RUG``) on the MetaRoom's floor under the table."""
