from django.apps import AppConfig


class ChainworkerConfig(AppConfig):
    name = "chainworker"
