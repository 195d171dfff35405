"""Ready-made market brokers (``beehave.agents.market``): bids from a path planner."""

from behaviours.market.brokers import TravelBroker

__all__ = ["TravelBroker"]
