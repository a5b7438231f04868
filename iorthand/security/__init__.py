"""Security: certificates (:mod:`.certs`), the router's TLS/mTLS/ACL configuration (:mod:`.acl`), diagnosis of
failed connections (:mod:`.diagnose`) and edge-side defence in depth (:mod:`.identity`)."""
