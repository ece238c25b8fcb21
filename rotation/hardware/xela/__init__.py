"""Xela uSkin: the reader of the vendor's xela_server stream."""
