"""The project's user-facing error: bad input or an impossible request, reported as one clear line."""


class ContactbenchError(ValueError):
    """Raised for input a user can fix (a malformed dataset, a model that does not apply to a dataset, ...)."""


class NotApplicable(ContactbenchError):
    """A model that does not apply to a dataset (e.g. a single-body model on several bodies): a sweep skips the job."""
