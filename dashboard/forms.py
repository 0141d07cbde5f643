"""The dashboard's query forms: what a page's address may ask for, checked before a service reads it."""

from __future__ import annotations

from typing import Any

from django import forms
from django.core.exceptions import ValidationError

from robots import labels

from .services import FLEET_SORTS, FLEET_STATES, FleetQuery


class FleetQueryForm(forms.Form):
    """The fleet page's address: ``?q=&state=&sort=&page=``.

    ``q`` matches ids and names, or is a label selector when it holds ``=`` (as in the search box).
    """

    q = forms.CharField(required=False, max_length=200)
    state = forms.ChoiceField(choices=[(state, state) for state in FLEET_STATES], required=False)
    sort = forms.ChoiceField(choices=[(s, s) for key in FLEET_SORTS for s in (key, f"-{key}")], required=False)
    # Bounded so the offset it makes stays far inside PostgreSQL's bigint.
    page = forms.IntegerField(min_value=1, max_value=10**9, required=False)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.selector: labels.Selector | None = None

    def clean_q(self) -> str:
        text = self.cleaned_data["q"]
        if "=" in text:
            try:
                self.selector = labels.parse_selector(text, field="q")
            except ValidationError as exc:
                raise ValidationError(exc.message_dict["q"]) from None
        return text

    def query(self) -> FleetQuery:
        """Return what the address asks for; a bad parameter is left at its default, a bad selector matches nothing."""
        self.is_valid()
        data = self.cleaned_data
        error = " ".join(self.errors.get("q", []))
        return FleetQuery(
            text=data.get("q", self.data.get("q", "")).strip(),
            selector=self.selector,
            state=data.get("state") or "all",
            sort=data.get("sort") or "id",
            page=data.get("page") or 1,
            error=error,
        )
