"""``--metrics HOST:PORT``: Prometheus metrics and a health check for ``pyrtu poll
--config``, ``pyrtu bridge``, ``pyrtu gateway`` and ``pyrtu simulate`` (docs/METRICS.md).

`pyrtu.metrics.address` is what the commands import (it needs no client library);
the rest needs ``prometheus_client`` (``pip install 'pyrtu[metrics]'``)."""
