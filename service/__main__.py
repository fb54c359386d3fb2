"""``python -m narf_service [--models DIR] [--host H] [--port P]``: run the service."""

from narf_service.main import main

raise SystemExit(main())
