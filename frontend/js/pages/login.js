// Login page.
import { api } from "../core/api.js";
import { el, showError, clearError } from "../core/ui.js";

export function mount(root, { params, onLogin }) {
  const user = el("input", { id: "username", name: "username", autocomplete: "username", required: true, autofocus: true });
  const pass = el("input", { id: "password", name: "password", type: "password", autocomplete: "current-password", required: true });
  const btn = el("button", { type: "submit", class: "primary" }, "Log in");
  const form = el(
    "form",
    { class: "card login", "aria-labelledby": "login-title" },
    el("h1", { id: "login-title" }, "Log in to OccuFly Studio"),
    el("label", { for: "username" }, "User name"),
    user,
    el("label", { for: "password" }, "Password"),
    pass,
    btn,
  );
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    clearError();
    btn.disabled = true;
    btn.textContent = "Logging in…";
    try {
      const r = await api.post("/auth/login", { username: user.value.trim(), password: pass.value });
      onLogin(r.user, params.next);
    } catch (err) {
      showError(err);
      pass.select();
    } finally {
      btn.disabled = false;
      btn.textContent = "Log in";
    }
  });
  root.append(form);
  user.focus();
  return {};
}
