"""Scene files that travel with the work: a Mitsuba XML scene and the files it references,
packed into one blob of bytes for workers on other machines (issue 27).

>>> b = bundle("room/scene.xml")         # doctest: +SKIP
>>> b["xml"], b["files"]                  # doctest: +SKIP
('scene.xml', ['meshes/floor.ply', 'scene.xml', 'tex/wood.png'])
>>> materialise(b)                        # on a worker: the XML's path there  # doctest: +SKIP
'/tmp/glossrt-scenes/4f1c.../scene.xml'

:func:`bundle` reads the XML, collects the files it references -- ``<string
name="filename" value=...>`` anywhere, ``filename`` attributes (``<include>``,
``<spectrum>``), recursively through included XML files -- relative to the folder of the XML
that names them (else, as Mitsuba's file resolver does, relative to the main XML's folder),
and packs them into an uncompressed tar in a fixed order with fixed metadata, so equal scenes
give equal bytes and an equal SHA-256 ``digest``. Paths keep their layout relative to the
deepest folder holding all of them. Left as they are, and so required on every node at the
same place: absolute references and references through ``$parameters``. A relative
reference to a file that does not exist is one :class:`~glossrt.errors.GlossrtError` naming
it, before any work; so is a bundle over :data:`MAX_BYTES`.

:func:`materialise` unpacks a bundle once per node into ``<GLOSSRT_SCENE_DIR or
/tmp/glossrt-scenes>/<digest>/``: into a temporary folder first, then renamed into place (a
worker that loses the race to another on the same node uses the winner's folder); tar
members that are not plain files or folders, or whose path leaves the folder, are refused.
A bundle's ``data`` may be a handle that ``fetch`` turns into the bytes (a Ray object
reference: :func:`glossrt.cluster.resolve`); it is fetched only when the node does not have
the folder yet.

Ground floor: plain Python (``xml.etree``, ``tarfile``, ``hashlib``).
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import tarfile
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable

from .errors import GlossrtError

#: the largest bundle (bytes of its files together)
MAX_BYTES = 2 * 1024 ** 3
ENV = "GLOSSRT_SCENE_DIR"
DEFAULT_DIR = os.path.join(tempfile.gettempdir(), "glossrt-scenes")


def _references(xml: str, main_dir: str, seen: set[str], out: set[str]) -> None:
    """Add the files ``xml`` references (and those its included XMLs reference) to ``out``."""
    if os.path.realpath(xml) in seen:  # (an include cycle)
        return
    seen.add(os.path.realpath(xml))
    out.add(xml)
    try:
        root = ET.parse(xml).getroot()
    except (OSError, ET.ParseError) as e:
        raise GlossrtError(f"scene file {xml}: cannot read it as XML ({e})") from None
    here = os.path.dirname(xml)
    for el in root.iter():
        refs = []
        if el.get("filename") is not None:
            refs.append(el.get("filename"))
        if el.tag == "string" and el.get("name") == "filename" and el.get("value") is not None:
            refs.append(el.get("value"))
        for ref in refs:
            if "$" in ref or os.path.isabs(ref):
                continue  # must exist on every node (documented)
            # both places Mitsuba may look, so the workers resolve it as the driver did
            found = [p for p in dict.fromkeys((os.path.abspath(os.path.join(here, ref)),
                                               os.path.abspath(os.path.join(main_dir, ref))))
                     if os.path.isfile(p)]
            if not found:
                raise GlossrtError(f"scene file {xml} references {ref!r}, which does not "
                                   f"exist (looked in {here})")
            for p in found:
                if el.tag == "include":
                    _references(p, main_dir, seen, out)
                else:
                    out.add(p)


def bundle(xml_path) -> dict:
    """The XML scene ``xml_path`` and the files it references as plain data (see the
    module): ``xml`` (the XML's path inside the bundle), ``digest`` (SHA-256 hex of
    ``data``), ``data`` (the tar's bytes) and ``files`` (paths inside the bundle, sorted)."""
    path = os.fspath(xml_path)
    if not os.path.isfile(path):
        raise GlossrtError(f"scene file not found: {path}")
    main = os.path.abspath(path)
    found: set[str] = set()
    _references(main, os.path.dirname(main), set(), found)
    base = os.path.commonpath([os.path.dirname(p) for p in found])
    names = {os.path.relpath(p, base).replace(os.sep, "/"): p for p in found}
    total = sum(os.path.getsize(p) for p in names.values())
    if total > MAX_BYTES:
        raise GlossrtError(f"scene {path}: its files hold {total / 2 ** 30:.2f} GiB, more than "
                           f"the {MAX_BYTES / 2 ** 30:.0f} GiB a bundle may carry; put them "
                           "on a folder every node mounts and give absolute paths")
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.GNU_FORMAT) as tar:
        for name in sorted(names):
            with open(names[name], "rb") as f:
                data = f.read()
            info = tarfile.TarInfo(name)
            info.size, info.mode, info.mtime = len(data), 0o644, 0
            tar.addfile(info, io.BytesIO(data))
    data = buf.getvalue()
    return {"xml": os.path.relpath(main, base).replace(os.sep, "/"),
            "digest": hashlib.sha256(data).hexdigest(), "data": data,
            "files": sorted(names)}


def scene_dir() -> str:
    """The node-local folder bundles are unpacked under (env ``GLOSSRT_SCENE_DIR``)."""
    return os.environ.get(ENV) or DEFAULT_DIR


def _safe_name(name: str, what: str) -> str:
    norm = os.path.normpath(name)
    if (not name or os.path.isabs(name) or norm == ".." or norm.startswith(".." + os.sep)
            or "\\" in name):
        raise GlossrtError(f"scene bundle: {what} {name!r} leaves the bundle's folder")
    return norm


def _unpack(data: bytes, dest: str) -> None:
    try:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:") as tar:
            members = tar.getmembers()
            for m in members:
                norm = _safe_name(m.name, "member")
                if not (m.isfile() or m.isdir()):
                    raise GlossrtError(f"scene bundle: member {m.name!r} is not a plain file "
                                       "or folder")
                target = os.path.join(dest, norm)
                if m.isdir():
                    os.makedirs(target, exist_ok=True)
                    continue
                os.makedirs(os.path.dirname(target), exist_ok=True)
                src = tar.extractfile(m)
                assert src is not None
                with open(target, "wb") as f:
                    shutil.copyfileobj(src, f)
    except tarfile.TarError as e:
        raise GlossrtError(f"scene bundle: not a valid tar ({e})") from None


def materialise(scene, fetch: Callable | None = None) -> str:
    """The path of the scene on this node: a ``str`` (a built-in name or a path) as it is; a
    :func:`bundle` dict unpacked once per node under :func:`scene_dir` (see the module).
    ``fetch``: turns a bundle's ``data`` that is not bytes (e.g. a Ray object reference)
    into the bytes; called only when this node does not have the bundle yet."""
    if isinstance(scene, (str, os.PathLike)):
        return os.fspath(scene)
    if not isinstance(scene, dict) or not {"xml", "digest", "data"} <= set(scene):
        raise GlossrtError(f"not a scene bundle: {type(scene).__name__}")
    digest = str(scene["digest"])
    if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
        raise GlossrtError(f"scene bundle: bad digest {digest!r}")
    xml = _safe_name(str(scene["xml"]), "XML path")
    root = scene_dir()
    target = os.path.join(root, digest)
    if not os.path.isdir(target):
        data = scene["data"]
        if not isinstance(data, (bytes, bytearray, memoryview)):
            if fetch is None:
                raise GlossrtError("scene bundle: its data is a handle and no fetch was given")
            data = fetch(data)
        if hashlib.sha256(data).hexdigest() != digest:
            raise GlossrtError(f"scene bundle {digest[:12]}: its data does not match its digest")
        os.makedirs(root, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=f".{digest[:16]}.", dir=root)
        try:
            _unpack(bytes(data), tmp)
            try:
                os.rename(tmp, target)
            except OSError:
                if not os.path.isdir(target):  # not a lost race
                    raise
        finally:
            if os.path.isdir(tmp):
                shutil.rmtree(tmp, ignore_errors=True)
    out = os.path.join(target, xml)
    if not os.path.isfile(out):
        raise GlossrtError(f"scene bundle {digest[:12]}: {scene['xml']!r} is missing from "
                           f"{target}")
    return out
