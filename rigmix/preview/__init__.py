"""Previews of characters and their clips: the offscreen renderer (:mod:`rigmix.preview.render`)
and the web viewer."""
