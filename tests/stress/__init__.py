"""Stress suite of fastmem (issue 6): hard cases x solver variants; see cases.py."""
