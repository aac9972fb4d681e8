"""HTTP routers, one per resource; :mod:`service.app` assembles them."""
