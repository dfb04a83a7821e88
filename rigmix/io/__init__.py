"""File formats: files <-> :class:`rigmix.character.Character`.

The only place where conventions change (e.g. USD's row-vector matrices).
"""
