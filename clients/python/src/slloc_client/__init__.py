"""Python client of the slloc visual localization service (v1 API).

>>> from slloc_client import Client
>>> with Client("http://127.0.0.1:8000") as slloc:
...     print(slloc.health().status)
"""

from slloc_client import models
from slloc_client.client import Client, ImageInput
from slloc_client.errors import ProblemError, SllocError

__all__ = ["Client", "ImageInput", "ProblemError", "SllocError", "models"]
