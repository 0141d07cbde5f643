// The navigation's organization picker: picking one posts the form, so every page shows that organization.

const select = document.getElementById("org-picker-select");
select?.addEventListener("change", () => select.form.requestSubmit());
