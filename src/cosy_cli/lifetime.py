"""Objects that hold a resource (an OpenGL renderer, mostly) until :meth:`Closing.close`.

Kept free of imports so that classes in any package can share it without importing OpenGL."""

from __future__ import annotations


class Closing:
    """Base of resource owners: ``with Owner(...) as o:`` calls :meth:`close` on the way out
    (also on errors); subclasses define :meth:`close` (freeing twice must be harmless)."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
