"""The errors a job raises when the request itself cannot be done, as opposed to a bad option or a bug.

    bad option         ValueError          a value out of range, a path that is a file, an unknown name
    refused request    RequestRefused      well formed but impossible: no grasp fits the object, nothing to
                                           resume, no usable session, a bundle that names a missing encoder
    failed job         JobFailed           it started and could not finish (ranks diverged, touch unusable)

`rotate` prints each as one line on stderr and exits with status 2 for a bad option and 1 for a refused request or
a failed job; `rotate --debug ...` (or ROTATE_DEBUG=1) shows the traceback instead. Any other exception is a bug and
keeps its traceback. RequestRefused is a ValueError, so code that catches bad input keeps catching it.
"""

from __future__ import annotations


class RequestRefused(ValueError):
    """The request is well formed but cannot be done as asked; the message says what, why and what to try."""


class JobFailed(RuntimeError):
    """A job that started could not finish; the message says what failed and where its outputs are."""
