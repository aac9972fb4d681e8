"""HTTP routers, one per resource; :mod:`overlapmamba.service.app` assembles them."""
