// Entry point: hash router (#/login, #/annotate, #/review, #/admin), session, global error
// reporting. Pages are modules exporting mount(root, ctx) -> {unmount?()}.

import { api, ApiError } from "./core/api.js";
import { el, showError, clearError } from "./core/ui.js";
import { notificationBadge } from "./pages/corrections.js";

const PAGES = {
  login: { load: () => import("./pages/login.js"), title: "Log in", roles: null },
  annotate: { load: () => import("./pages/annotator.js"), title: "Annotate", roles: ["annotator", "admin"] },
  review: { load: () => import("./pages/reviewer.js"), title: "Review", roles: ["reviewer", "admin"] },
  admin: { load: () => import("./pages/admin.js"), title: "Admin", roles: ["admin"] },
};
const HOME = { annotator: "annotate", reviewer: "review", admin: "admin" };

export const session = { user: null };
let current = null;
let routing = Promise.resolve();

export function parseHash(hash = location.hash) {
  const h = hash.replace(/^#\/?/, "");
  const [name, query = ""] = h.split("?");
  return { name: name || "", params: Object.fromEntries(new URLSearchParams(query)) };
}

/** Change one or more query parameters of the current route without re-mounting. */
export function setParams(params) {
  const { name, params: cur } = parseHash();
  const q = new URLSearchParams({ ...cur, ...params });
  for (const [k, v] of Object.entries(params)) if (v === null || v === undefined) q.delete(k);
  history.replaceState(null, "", `#/${name}${q.toString() ? "?" + q : ""}`);
}

export function go(name, params = {}) {
  const q = new URLSearchParams(params).toString();
  location.hash = `#/${name}${q ? "?" + q : ""}`;
}

function renderNav() {
  const nav = document.getElementById("nav");
  const who = document.getElementById("whoami");
  const u = session.user;
  const { name } = parseHash();
  nav.replaceChildren(
    ...(u
      ? Object.entries(PAGES)
          .filter(([, p]) => p.roles && p.roles.includes(u.role))
          .map(([k, p]) => el("a", { href: `#/${k}`, "aria-current": k === name ? "page" : null }, p.title))
      : []),
  );
  who.replaceChildren(
    ...(u
      ? [
          el("span", {}, `${u.username} (${u.role})`),
          notificationBadge(),
          el("button", { type: "button", class: "link", onclick: logout }, "Log out"),
        ]
      : []),
  );
}

async function logout() {
  try {
    if (current?.unmount) await current.unmount();
    current = null;
    await api.send("POST", "/auth/logout");
  } catch (e) {
    showError(e);
  }
  session.user = null;
  go("login");
}

async function doRoute() {
  const { name, params } = parseHash();
  if (current?.unmount) {
    try {
      await current.unmount();
    } catch (e) {
      showError(e);
    }
  }
  current = null;
  clearError();
  const main = document.getElementById("main");
  if (!session.user && name !== "login") {
    try {
      session.user = await api.get("/auth/me");
    } catch (e) {
      if (!(e instanceof ApiError) || e.status !== 401) showError(e);
      go("login", name ? { next: location.hash.slice(1) } : {});
      return;
    }
  }
  let page = PAGES[name];
  if (!page) {
    go(session.user ? HOME[session.user.role] || "review" : "login");
    return;
  }
  if (page.roles && !page.roles.includes(session.user.role)) {
    main.replaceChildren(
      el("section", { class: "card" }, el("h1", {}, "Not available"), el("p", {}, `The ${page.title} page needs the role ${page.roles.join(" or ")}; you are logged in as ${session.user.role}.`)),
    );
    renderNav();
    return;
  }
  document.title = `${page.title} · OccuFly Studio`;
  document.body.dataset.page = name;
  renderNav();
  main.replaceChildren(el("p", { class: "loading" }, `Loading ${page.title}…`));
  try {
    const mod = await page.load();
    main.replaceChildren();
    current = (await mod.mount(main, { params, session, go, setParams, onLogin: onLogin })) || null;
  } catch (e) {
    main.replaceChildren(el("section", { class: "card" }, el("h1", {}, `${page.title} could not be opened`), el("p", {}, e.message || String(e))));
    showError(e);
  }
}

function onLogin(user, next) {
  session.user = user;
  if (next) location.hash = `#${next}`;
  else go(HOME[user.role] || "review");
}

function route() {
  routing = routing.then(doRoute, doRoute);
  return routing;
}

window.addEventListener("hashchange", route);
window.addEventListener("error", (e) => showError(e.error || e.message));
window.addEventListener("unhandledrejection", (e) => showError(e.reason));
route();
