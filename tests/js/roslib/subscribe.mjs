// Subscribe to one topic with roslib (npm) through a rosbridge URL; print one JSON line per event.
// Usage: node subscribe.mjs URL TOPIC TYPE COUNT
import { Ros, Topic } from "roslib";

const [url, name, messageType, count] = process.argv.slice(2);
const say = (event) => console.log(JSON.stringify(event));
const ros = new Ros({ url });
const topic = new Topic({ ros, name, messageType });
let received = 0;

setTimeout(() => {
  say({ event: "timeout", received });
  process.exit(4);
}, 20000);
ros.on("error", (error) => {
  say({ event: "error", message: String(error?.message ?? error) });
  process.exit(2);
});
ros.on("close", () => {
  say({ event: "close", received });
  process.exit(received >= Number(count) ? 0 : 3);
});
ros.on("connection", () => say({ event: "connected" }));
topic.subscribe((message) => {
  received += 1;
  say({ event: "message", message });
  if (received >= Number(count)) {
    topic.unsubscribe();
    ros.close();
  }
});
