"""The controllers' protocols as bytes in, values out (sans-IO: no socket, no serial line, no event loop)."""
