"""The limb worker process: ``python -m client --connect tcp://HOST:5555`` (see ``client.worker``)."""
