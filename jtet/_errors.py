"""Exceptions raised by jtet. Every message says what is wrong and where."""


class JtetError(Exception):
    """Base class of every error jtet raises on purpose."""


class MeshInputError(JtetError, ValueError):
    """The mesh given to jtet is not a valid tetrahedral mesh (NaN, bad index, cell type...)."""


class MeshFileError(JtetError, OSError):
    """A mesh file is missing, unreadable, or in a format jtet cannot read or write."""


class InvariantError(JtetError, RuntimeError):
    """An operation broke a mesh invariant; raised by the optional invariant checks."""
