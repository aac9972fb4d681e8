"""Python clients, CLI and fleet simulator for the service (httpx). Built by issue 8."""
