"""Elastic resource allocation: profiles, Algorithm 1, runtime adaptation."""
