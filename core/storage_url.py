"""Where envelopes are kept, from one setting: ENVELOPE_STORAGE_URL.

Empty (the default, what `make run` uses): the local disk under MEDIA_ROOT/envelopes. `s3://BUCKET`
or `s3://BUCKET/PREFIX`: an S3 bucket (AWS, or any S3 server such as SeaweedFS or MinIO), at
the endpoint ENVELOPE_S3_ENDPOINT_URL (empty: AWS's), with the credentials boto3 finds in the
environment (AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, or an instance role). Read by the
settings, so nothing here imports Django.
"""

from pathlib import Path
from urllib.parse import urlsplit

LOCAL_BACKEND = "sharing.storage.DurableFileSystemStorage"
S3_BACKEND = "sharing.storage.DurableS3Storage"


class StorageUrlError(ValueError):
    """ENVELOPE_STORAGE_URL cannot be used; the message says why."""


def envelope_storage_config(
    url: str, *, media_root: Path, endpoint_url: str = "", region: str = ""
) -> dict:
    """The STORAGES["envelopes"] entry for `url`."""
    if not url:
        return {"BACKEND": LOCAL_BACKEND, "OPTIONS": {"location": str(media_root / "envelopes")}}
    parts = urlsplit(url)
    if parts.scheme != "s3":
        raise StorageUrlError(
            f"ENVELOPE_STORAGE_URL must be empty (local disk) or s3://BUCKET[/PREFIX], not {url!r}"
        )
    if not parts.netloc or parts.query or parts.fragment:
        raise StorageUrlError(f"ENVELOPE_STORAGE_URL {url!r} names no bucket, or has extras")
    options = {
        "bucket_name": parts.netloc,
        "location": parts.path.strip("/"),
        # Envelope names are record ids: an existing object is never replaced by a new one.
        "file_overwrite": False,
        "default_acl": None,
        "querystring_auth": False,
    }
    if endpoint_url:
        options["endpoint_url"] = endpoint_url
    if region:
        options["region_name"] = region
    return {"BACKEND": S3_BACKEND, "OPTIONS": options}
