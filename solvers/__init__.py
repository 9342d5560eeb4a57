"""Inverse problems built on jaxsh."""
