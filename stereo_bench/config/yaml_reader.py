"""YAML read as a rig file is read: keys unique, and the document's size measured before any
Python object is built, so that an alias bomb (a kilobyte that expands to billions of values)
or an alias that contains itself is refused in milliseconds, naming the file.
"""

from __future__ import annotations


import yaml

from ..core.files import UnreadableFileError, read_text
from .bounds import ConfigError, MAX_FILE_BYTES, MAX_NESTING, MAX_NODES


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (the plain loader keeps the
    last one, so a second ``cameras:`` would silently drop the first list)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


def _expanded_shape(node, source: str, what: str) -> None:
    """Refuse a composed YAML document whose data, with every alias expanded, would hold more
    than MAX_NODES nodes or nest more than MAX_NESTING levels, or which refers to itself.

    Aliases make the composed document a graph: nine levels of nine aliases are 1.3 KB of text
    and 9^9 nodes of data, which every consumer (validation, a fingerprint, a copy) walks in full.
    Each distinct node is measured once (sizes and depths of shared nodes are memoised), so the
    check costs the text's size, not the expansion's."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    open_nodes: set[int] = set()
    stack = [(node, False)]
    while stack:
        n, children_done = stack.pop()
        key = id(n)
        kids = ([c for pair in n.value for c in pair] if isinstance(n, yaml.MappingNode)
                else n.value if isinstance(n, yaml.SequenceNode) else [])
        if children_done:
            open_nodes.discard(key)
            size[key] = 1 + sum(size[id(c)] for c in kids)
            depth[key] = 1 + max((depth[id(c)] for c in kids), default=0)
            if size[key] > MAX_NODES:
                raise ConfigError(f"{source}: expands to more than {MAX_NODES:,} values once its "
                                  f"aliases are resolved; expected a {what}")
            if depth[key] > MAX_NESTING:
                raise ConfigError(f"{source}: nested more than {MAX_NESTING} levels deep; "
                                  f"expected a {what}")
            continue
        if key in size:
            continue
        if key in open_nodes:
            raise ConfigError(f"{source}: an alias refers to a node that contains it; expected "
                              f"a {what}")
        open_nodes.add(key)
        stack.append((n, True))
        stack.extend((c, False) for c in kids if id(c) not in size)


def load_yaml(path, what: str = "rig file"):
    """The data of a YAML file, or a ConfigError naming the file: unreadable, too large, not
    UTF-8 text, not YAML, nested too deeply, or with a duplicate key."""
    try:
        text = read_text(path, what, MAX_FILE_BYTES)
    except FileNotFoundError:
        raise ConfigError(f"{path}: cannot read {what} (no such file)") from None
    except UnreadableFileError as e:
        raise ConfigError(str(e)) from None
    return parse_yaml(text, str(path), what)


def parse_yaml(text: str, source: str, what: str = "rig file"):
    """The data of YAML ``text`` (a file's, or a form's), or a ConfigError naming ``source``:
    too large, not YAML, nested too deeply or expanding too far (aliases), or with a duplicate
    key."""
    if len(text.encode("utf-8", "replace")) > MAX_FILE_BYTES:
        raise ConfigError(f"{source}: a {what} is expected to be under {MAX_FILE_BYTES:,} bytes")
    if "\x00" in text:
        raise ConfigError(f"{source}: contains NUL characters; expected a {what} in YAML")
    try:
        # Composing is iterative in PyYAML; only the shape check below stands between a
        # 10,000-deep document (or an alias bomb) and a RecursionError (or a hang) later.
        node = yaml.compose(text, Loader=_UniqueKeyLoader)
        if node is None:
            return None
        _expanded_shape(node, source, what)
        loader = _UniqueKeyLoader(text)
        try:
            return loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: not valid YAML ({e})") from None
    except RecursionError:
        raise ConfigError(f"{source}: nested too deeply; expected a {what}") from None
