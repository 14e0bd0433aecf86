// DOM helpers: element builder, status/error messages, modal dialogs, small formatters.

/** el("button", {class: "x", onclick: fn}, "text", child) */
export function el(tag, attrs = {}, ...children) {
  const n = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith("on") && typeof v === "function") n.addEventListener(k.slice(2), v);
    else if (k === "class") n.className = v;
    else if (k === "dataset") Object.assign(n.dataset, v);
    else if (k === "style" && typeof v === "object") Object.assign(n.style, v);
    else if (v === true) n.setAttribute(k, "");
    else n.setAttribute(k, String(v));
  }
  for (const c of children.flat()) {
    if (c === undefined || c === null || c === false) continue;
    n.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return n;
}

/** Show a readable error in the page's alert region (never a blank page). */
export function showError(err, where = null) {
  const msg = typeof err === "string" ? err : err && err.message ? err.message : String(err);
  const box = where || document.getElementById("alert");
  if (!box) return;
  box.replaceChildren(
    el("span", {}, msg),
    el("button", { class: "link", type: "button", "aria-label": "Dismiss message", onclick: () => box.replaceChildren() }, "×"),
  );
  box.hidden = false;
  // API errors are expected answers (shown above); anything else is a bug worth a console error
  if (err && typeof err !== "string") (err.name === "ApiError" ? console.warn : console.error)(err);
}

export function clearError() {
  const box = document.getElementById("alert");
  if (box) box.replaceChildren();
}

let toastTimer = null;
/** A short polite status message (screen readers announce it). */
/** A short message at the bottom; `action` ({label, run, id?}) adds one button (e.g. Undo),
 * shown for `ms` (8 s with an action) and clickable; the next toast replaces it. */
export function toast(msg, { action = null, ms = null } = {}) {
  const t = document.getElementById("toast");
  if (!t) return;
  t.replaceChildren(msg);
  t.classList.toggle("has-action", !!action);
  if (action) {
    const b = document.createElement("button");
    b.type = "button";
    b.className = "link toast-action";
    if (action.id) b.id = action.id;
    b.textContent = action.label;
    b.addEventListener("click", () => {
      b.disabled = true;
      t.classList.remove("show", "has-action");
      action.run();
    });
    t.append(" ", b);
  }
  t.classList.add("show");
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => t.classList.remove("show", "has-action"), ms ?? (action ? 8000 : 3500));
}

/**
 * Modal dialog. buttons: [{label, value, primary?}]. Resolves with the chosen value
 * (Escape resolves with `cancelValue`).
 */
export function dialog({ title, body, buttons, cancelValue = null }) {
  return new Promise((resolve) => {
    const d = el("dialog", { class: "modal", "aria-labelledby": "dlg-title" });
    const done = (v) => {
      d.close();
      d.remove();
      resolve(v);
    };
    d.append(
      el("h2", { id: "dlg-title" }, title),
      el("div", { class: "dlg-body" }, body),
      el(
        "div",
        { class: "dlg-buttons" },
        buttons.map((b) => el("button", { type: "button", class: b.primary ? "primary" : "", onclick: () => done(b.value) }, b.label)),
      ),
    );
    d.addEventListener("cancel", (e) => {
      e.preventDefault();
      done(cancelValue);
    });
    document.body.append(d);
    d.showModal();
    d.querySelector("button.primary, button")?.focus();
  });
}

export function pct(x, digits = 1) {
  return x === null || x === undefined || Number.isNaN(x) ? "–" : `${(100 * x).toFixed(digits)} %`;
}

export function fmtDate(s) {
  if (!s) return "";
  const d = new Date(s);
  return Number.isNaN(d.getTime()) ? String(s) : d.toLocaleString();
}

export function downloadBlob(blob, name) {
  const a = el("a", { href: URL.createObjectURL(blob), download: name });
  document.body.append(a);
  a.click();
  setTimeout(() => {
    URL.revokeObjectURL(a.href);
    a.remove();
  }, 1000);
}

/** A <table> from rows of objects; columns: [{key, label, fmt?}] */
export function table(rows, columns, { caption = null, rowAttrs = null } = {}) {
  return el(
    "table",
    {},
    caption ? el("caption", {}, caption) : null,
    el("thead", {}, el("tr", {}, columns.map((c) => el("th", { scope: "col", "data-col": c.key }, c.label)))),
    el(
      "tbody",
      {},
      rows.map((r) =>
        el(
          "tr",
          rowAttrs ? rowAttrs(r) : {},
          columns.map((c) => el("td", { "data-col": c.key }, c.fmt ? c.fmt(r[c.key], r) : r[c.key] ?? "")),
        ),
      ),
    ),
  );
}
