"""The project's user-facing error: bad input or an impossible request, reported as one clear line."""


class ContactbenchError(ValueError):
    """Raised for input a user can fix (a malformed dataset, a model that does not apply to a dataset, ...)."""


class RecordingsError(ContactbenchError):
    """A dataset that does not follow the recordings format; the message names file, field and place."""


class NotApplicable(ContactbenchError):
    """A model that does not apply to a dataset (e.g. a single-body model on several bodies): a sweep skips the job."""


def require_positive_integers(settings: dict[str, object], optional: tuple[str, ...] = ()) -> None:
    """Refuse any model.module setting that is not a positive integer (those named in `optional` may be None)."""
    for name, value in settings.items():
        if value is None and name in optional:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            expected = "a positive integer" + (" or null" if name in optional else "")
            raise ContactbenchError(f"model.module.{name} is {value!r} (expected {expected})")
