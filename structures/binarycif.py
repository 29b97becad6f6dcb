"""BinaryCIF, the PDB's binary mmCIF (msgpack with column encodings), read by wwPDB's own
py-mmcif and handed to the mmCIF reader as text: one reader of models, whatever their packing.

py-mmcif logs and swallows a decoding failure (an empty result), and reads a locator that looks
like a URL from the network: only absolute local paths are passed, and an empty result is
refused here, naming the file.
"""

from __future__ import annotations

import logging
import os

from structures.errors import StructureError

logging.getLogger("mmcif").setLevel(logging.CRITICAL)  # a refusal is ours to word


def to_mmcif(path: str, folder: str) -> str:
    """`path`'s first data block written as mmCIF text into `folder` (the path returned)."""
    name = os.path.basename(path)
    try:
        from mmcif.io.BinaryCifReader import BinaryCifReader
        from mmcif.io.PdbxWriter import PdbxWriter
    except ImportError:  # pragma: no cover - depends on the install
        raise StructureError("reading BinaryCIF needs py-mmcif: pip install mmcif") from None
    containers = BinaryCifReader().deserialize(os.path.abspath(path))
    if not containers:
        raise StructureError(f"cannot read {name}: it is not BinaryCIF (or it is damaged)")
    block = containers[0]
    if not block.exists("atom_site") or block.getObj("atom_site").getRowCount() == 0:
        raise StructureError(f"{name} has no atom_site rows; is it a BinaryCIF model file?")
    stem = name[: -len(".gz")] if name.lower().endswith(".gz") else name
    out = os.path.join(folder, f"{stem}.cif")
    with open(out, "w", encoding="utf-8") as fh:
        PdbxWriter(fh).write([block])
    return out
