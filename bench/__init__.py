"""fastmem benchmark suite: each module runs as ``python -m bench.<name>`` and writes JSON."""
