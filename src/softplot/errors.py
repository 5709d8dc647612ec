"""Errors that reach the user as one line (the CLI prints them and exits with code 2)."""


class SoftplotError(Exception):
    """Bad input or an impossible request; the message is one line naming the problem."""


class CertificateError(SoftplotError):
    """A camera certificate is malformed: the message names the file and the field."""


class ScanError(SoftplotError):
    """A scan cannot be read: missing, empty, corrupt or of an unsupported kind."""
