"""Deploying a secured site: the site's certificates (:mod:`agent.deploy.certs`) and the
Zenoh configuration of every role with TLS, mutual authentication and access control
(:mod:`agent.deploy.zenoh_config`); ``uma deploy`` drives them (:mod:`agent.cli.deploy`)."""
