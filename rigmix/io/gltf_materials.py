"""glTF materials and images -> :class:`rigmix.character.Material` / :class:`Texture`.

Images come from a buffer view, a ``data:`` URI or a file next to the glTF; only PNG and JPEG
(recognized by their bytes) are kept, anything else drops the texture with a warning.
"""

from __future__ import annotations

from ..character import Material, Texture
from .accessors import MAX_IMAGE_BYTES, Document, decode_data_uri, read_regular_file

__all__ = ["read_materials"]


def _sniff_mime(data: bytes) -> str | None:
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "image/png"
    if data[:3] == b"\xff\xd8\xff":
        return "image/jpeg"
    return None


def _image(doc, index: int, log) -> tuple[bytes, str] | None:
    img = doc.get("images", index)
    label = f"images[{index}]" + (f" '{img['name']}'" if img.get("name") else "")
    if "bufferView" in img:
        data = bytes(doc.buffer_view(img["bufferView"], label))
    elif isinstance(img.get("uri"), str) and img["uri"].startswith("data:"):
        data, _ = decode_data_uri(img["uri"], doc, label, max_bytes=MAX_IMAGE_BYTES)
    elif isinstance(img.get("uri"), str):
        # confined like buffers (an error); only a file missing from the folder drops the texture
        path = doc.resolve_uri(img["uri"], label, must_exist=False)
        if path is None:
            log(f"{label}: {img['uri']!r} was not found next to the file: texture dropped")
            return None
        data = read_regular_file(path, limit=MAX_IMAGE_BYTES, name=doc.name, label=f"{label} ({img['uri']!r})")
    else:
        raise doc.error(f"{label} has neither a bufferView nor a uri")
    mime = _sniff_mime(data)
    if mime is None:
        log(f"{label}: not a PNG or JPEG image: texture dropped")
        return None
    return data, mime


def read_materials(doc: Document, log) -> tuple[Material, ...]:
    """Metallic-roughness materials with their base colour texture.

    Parameters
    ----------
    doc : Document
    log : callable
        Receives one message per texture that had to be dropped.

    Returns
    -------
    tuple of Material, in file order (primitives index them).
    """
    textures: dict[int, Texture | None] = {}

    def texture(ti: int) -> Texture | None:
        if ti not in textures:
            tex = doc.get("textures", ti)
            got = _image(doc, tex["source"], log) if "source" in tex else None
            sampler = {}
            if "sampler" in tex:
                smp = doc.get("samplers", tex["sampler"])
                sampler = {k: smp[k] for k in ("magFilter", "minFilter", "wrapS", "wrapT") if k in smp}
            name = tex.get("name") or ("source" in tex and doc.get("images", tex["source"]).get("name")) or ""
            textures[ti] = None if got is None else Texture(got[0], got[1], name, sampler)
        return textures[ti]

    out = []
    for mi, m in enumerate(doc.items("materials")):
        pbr = m.get("pbrMetallicRoughness", {})
        tex, texcoord = None, 0
        if "baseColorTexture" in pbr:
            tex = texture(pbr["baseColorTexture"]["index"])
            texcoord = int(pbr["baseColorTexture"].get("texCoord", 0))
        out.append(Material(
            name=m.get("name", "") or "",
            base_color=pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0]),
            metallic=float(pbr.get("metallicFactor", 1.0)),
            roughness=float(pbr.get("roughnessFactor", 1.0)),
            base_color_texture=tex,
            base_color_texcoord=texcoord,
            double_sided=bool(m.get("doubleSided", False)),
            alpha_mode=m.get("alphaMode", "OPAQUE"),
            alpha_cutoff=float(m.get("alphaCutoff", 0.5)),
            emissive=m.get("emissiveFactor", [0.0, 0.0, 0.0]),
            extra={"extras": m["extras"]} if m.get("extras") else {},
        ))
    return tuple(out)
